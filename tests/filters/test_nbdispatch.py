"""One compiled version per numba kernel (filters/nbdispatch.py): read-only, writable and
broadcast inputs reach the same compiled code, and the results do not depend on the flags."""
import numpy as np
import pytest

from filters import kernels

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba not installed")


def _frozen(a):
    a = np.array(a)
    a.flags.writeable = False
    return a


def _case(rng, N, n=4, m=3):
    A = rng.standard_normal((N, n, n))
    P = A @ np.swapaxes(A, -1, -2) + n * np.eye(n)
    F = np.eye(n) + 0.1 * rng.standard_normal((n, n))
    Q = 0.01 * np.eye(n)
    x = rng.standard_normal((N, n))
    H = rng.standard_normal((N, m, n))
    y = rng.standard_normal((N, m))
    r = 0.5 + rng.random(m)
    return x, P, F, Q, y, H, r


@pytest.mark.parametrize("N", [3, kernels.PARALLEL_MIN_TRIALS])
def test_read_only_and_writable_inputs_share_one_compiled_version(N):
    from filters import _nbkernels as k

    rng = np.random.default_rng(7)
    x, P, F, Q, y, H, r = _case(rng, N)
    out = []
    for wrap in (np.array, _frozen):  # writable, then read-only (as a bus payload or a frozen model matrix)
        Pp = kernels.cov_predict(wrap(F), wrap(P), wrap(Q), backend="numba")
        upd = kernels.predict_joseph_update(wrap(F), wrap(Q), wrap(x), wrap(P), wrap(y), wrap(H), wrap(r),
                                            backend="numba")
        R = np.diag(r)
        X = kernels.sigma_points(wrap(x), wrap(P), 1.5, backend="numba")
        K = X.shape[0]
        Wm = np.full(K, 1.0 / K)
        Z = np.einsum("kni,nmi->knm", X, H)
        # a shared R arrives as a stride-0 broadcast view, a per-trial R as a C array
        u1 = kernels.ukf_update(wrap(x), wrap(P), X, Z, wrap(y), wrap(R), Wm, Wm, backend="numba")
        u2 = kernels.ukf_update(wrap(x), wrap(P), X, Z, wrap(y), np.broadcast_to(R, (N, 3, 3)).copy(), Wm, Wm,
                                backend="numba")
        out.append((Pp, *upd, *u1, *u2))
    for a, b in zip(*out):
        np.testing.assert_array_equal(a, b)
    drv = "par" if N >= kernels.PARALLEL_MIN_TRIALS else "ser"
    for name in (f"predict_{drv}", f"joseph_{drv}", f"sigma_{drv}", f"ukf_update_{drv}"):
        assert len(getattr(k, name).signatures) == 1, (name, getattr(k, name).signatures)
    # the functions the drivers call: none when the drivers came from the on-disk cache, else one
    for name in ("_predict_block", "_joseph_block", "_sigma_block", "_ukf_update_block", "sparse_rows"):
        assert len(getattr(k, name).signatures) <= 1, (name, getattr(k, name).signatures)


def test_a_kernel_refuses_an_argument_of_another_dtype_instead_of_compiling_it():
    from filters import nbdispatch
    from filters import _nbkernels as k

    rng = np.random.default_rng(8)
    _, P, F, Q, *_ = _case(rng, 2)
    drv = nbdispatch.ready(k.predict_ser)
    with pytest.raises(TypeError):
        drv(F.astype(np.float32), P, Q)
    assert len(drv.signatures) == 1
