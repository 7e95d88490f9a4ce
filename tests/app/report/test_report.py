"""The run / experiment report (sitl.app.report): report.html is self-contained, embeds every
PNG written beside it byte for byte, its key-figure table holds the JSON document's values, it
opens in headless Chromium and shows a non-blank map; the map's ellipses are the stated
confidence of the stated covariance."""
from __future__ import annotations

import base64
import json
import math
import os
import re
import shutil
import signal
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from sitl.app.cli import main as skyfuse

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
DATA_PNG = "data:image/png;base64,"


class _Page(HTMLParser):
    """The report's <img> sources, key-figure rows (their data- attributes) and any script,
    link or remote source."""

    def __init__(self):
        super().__init__()
        self.imgs, self.rows, self.remote, self.scripts = [], [], [], 0

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.imgs.append(a)
        if tag == "tr" and "data-quantity" in a:
            self.rows.append(a)
        if tag in ("script", "link", "iframe", "object", "embed"):
            self.scripts += 1
        for k in ("src", "href"):
            if a.get(k) and re.match(r"^(https?:)?//", a[k]):
                self.remote.append(a[k])


def _page(out: Path) -> tuple[_Page, str]:
    text = (out / "report.html").read_text(encoding="utf-8")
    p = _Page()
    p.feed(text)
    return p, text


def _at(doc, path):
    for k in path:
        doc = doc[k]
    return doc


@pytest.fixture(scope="module")
def batch_run(tmp_path_factory):
    """`skyfuse demo --batch` for 60 simulated seconds (a few seconds warm)."""
    out = tmp_path_factory.mktemp("demo-batch")
    assert skyfuse(["demo", "--batch", "--duration", "60", "--seed", "3", "--quiet", "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def experiment_run(tmp_path_factory):
    """`skyfuse experiment ekf-vs-ukf` with 20 trials of 120 steps (about a second)."""
    out = tmp_path_factory.mktemp("ekf")
    assert skyfuse(["experiment", "ekf-vs-ukf", "--trials", "20", "--steps", "120", "--quiet", "--out", str(out)]) == 0
    return out


# the batch demo takes some 10 s on an idle machine (slow); the experiment about 3 s
BATCH = pytest.param("batch_run", marks=pytest.mark.slow)


@pytest.mark.parametrize("run", [BATCH, "experiment_run"])
def test_every_png_written_is_embedded_byte_for_byte_and_nothing_is_remote(run, request):
    out = request.getfixturevalue(run)
    page, text = _page(out)
    pngs = sorted(out.glob("*.png"))
    assert pngs, "no figure written"
    embedded = [i["src"] for i in page.imgs if i.get("src", "").startswith(DATA_PNG)]
    assert len(embedded) == len(page.imgs) == len(pngs)
    assert sorted(base64.b64decode(s[len(DATA_PNG):]) for s in embedded) == sorted(p.read_bytes() for p in pngs)
    assert page.scripts == 0 and page.remote == []


@pytest.mark.parametrize("run, document", [pytest.param("batch_run", "report.json", marks=pytest.mark.slow),
                                           ("experiment_run", "result.json")])
def test_the_tables_values_are_the_documents(run, document, request):
    out = request.getfixturevalue(run)
    doc = json.loads((out / document).read_text())
    page, _ = _page(out)
    by_path = {}
    for r in page.rows:
        if "data-path" not in r:
            assert r["data-source"] == "bus.log"  # computed by the report from the run's log
            continue
        path = json.loads(r["data-path"])
        want = _at(doc, path)
        if isinstance(want, dict):  # a counter by reason: the row is its total
            want = sum(want.values())
        assert float(r["data-value"]) == want, path
        if "data-band-path" in r:
            assert _at(doc, json.loads(r["data-band-path"])) is not None
        by_path[tuple(path)] = r
    if run == "batch_run":  # the run's RMSE of each target
        for target, e in doc["errors"].items():
            assert float(by_path[("errors", target, "rmse_m")]["data-value"]) == e["rmse_m"]
    else:  # the ANEES of both filters, each with its band
        for f in ("ekf", "ukf"):
            assert float(by_path[(f, "anees")]["data-value"]) == doc[f]["anees"]
            assert json.loads(by_path[(f, "anees")]["data-band-path"]) == [f, "anees_bounds_99"]


@pytest.mark.slow
def test_a_batch_run_reports_the_position_nees_of_each_target(batch_run):
    page, _ = _page(batch_run)
    doc = json.loads((batch_run / "report.json").read_text())
    nees = [r for r in page.rows if r.get("data-source") == "bus.log"]
    assert len(nees) == len(doc["errors"])
    assert all(float(r["data-value"]) > 0 for r in nees)


def _screenshot(html: Path, png: Path, tmp: Path, size=(1200, 900)) -> str:
    cmd = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", "--no-first-run",
           f"--user-data-dir={tmp / 'chromium-profile'}", f"--window-size={size[0]},{size[1]}",
           f"--screenshot={png}", html.resolve().as_uri()]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        _, err = proc.communicate(timeout=90)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        pytest.fail("chromium did not finish in 90 s")
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 0, err[-2000:]
    assert png.is_file(), err[-2000:]
    return err


@pytest.mark.live
@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="headless Chromium (Debian package 'chromium') is not installed")
def test_the_report_opens_in_headless_chromium_and_shows_the_map(batch_run, tmp_path):
    import matplotlib.image

    err = _screenshot(batch_run / "report.html", tmp_path / "report.png", tmp_path)
    assert "Uncaught" not in err and "Failed to load resource" not in err, err[-2000:]
    # the control: the same page with the map replaced by a white PNG of its size (same layout)
    h, w = matplotlib.image.imread(batch_run / "map.png").shape[:2]
    matplotlib.image.imsave(tmp_path / "white.png", np.ones((h, w, 3)))
    white = DATA_PNG + base64.b64encode((tmp_path / "white.png").read_bytes()).decode("ascii")
    html = (batch_run / "report.html").read_text(encoding="utf-8")
    blank = re.sub(r'(<img id="map-img" src=")[^"]*"', lambda m: m.group(1) + white + '"', html)
    assert blank != html
    (tmp_path / "blank.html").write_text(blank, encoding="utf-8")
    _screenshot(tmp_path / "blank.html", tmp_path / "blank.png", tmp_path)
    shot = matplotlib.image.imread(tmp_path / "report.png")[..., :3]
    ctrl = matplotlib.image.imread(tmp_path / "blank.png")[..., :3]
    # the map is the first thing under the title: 1100 px wide, about half as high
    region = (slice(120, 560), slice(40, 1100))
    m, c = shot[region], ctrl[region]
    assert float(m.std()) > 0.08, f"map area pixel std {m.std():.3f}: blank?"
    assert float(np.mean(np.any(m < 0.9, axis=-1))) > 0.03  # lines, labels, tracks: not all white
    assert float(c.std()) < 0.2 * float(m.std())  # and that is the map's doing


# ------------------------------------------------------------------ the map's geometry


def test_the_ellipse_has_the_stated_probability():
    from sitl.app.report.figures import ELLIPSE_P, ellipse_axes

    rng = np.random.default_rng(7)
    cov = np.array([[9.0, 4.0], [4.0, 4.0]])
    a, b, ang = ellipse_axes(cov)
    th = math.radians(ang)
    u = np.array([math.cos(th), math.sin(th)])
    v = np.array([-u[1], u[0]])
    x = rng.multivariate_normal([0.0, 0.0], cov, size=200_000)
    inside = (x @ u / a) ** 2 + (x @ v / b) ** 2 <= 1.0
    se = math.sqrt(ELLIPSE_P * (1 - ELLIPSE_P) / x.shape[0])
    assert abs(inside.mean() - ELLIPSE_P) < 4 * se
    # and the axes of a diagonal covariance: sqrt(-2 ln 0.05) sigma along east and north
    a, b, ang = ellipse_axes(np.diag([16.0, 1.0]))
    k = math.sqrt(-2.0 * math.log(0.05))
    assert (a, b) == pytest.approx((4 * k, k)) and abs(math.sin(math.radians(ang))) < 1e-12


def test_the_horizontal_covariance_is_the_east_north_marginal():
    from sitl.geodesy import enu_rotation
    from sitl.app.report.figures import horizontal_cov_m2

    ref = (math.radians(55.93), math.radians(37.52), 190.0)
    r = enu_rotation(ref[0], ref[1])
    enu_cov = np.array([[4.0, 1.0, 0.5], [1.0, 9.0, -2.0], [0.5, -2.0, 25.0]])  # e, n, u
    ecef_cov = r.T @ enu_cov @ r
    assert horizontal_cov_m2(ecef_cov, ref) == pytest.approx(enu_cov[0:2, 0:2])


def test_the_radar_site_is_its_offset_from_the_launch_pad():
    from sitl.geodesy import ecef_to_enu, geodetic_to_ecef
    from sitl.app.report.figures import radar_site

    sonde = {"launch": (55.93, 37.52, 190.0), "gcpp_offset_m": 300.0, "gcpp_bearing_deg": 140.0}
    lat, lon, h = radar_site(sonde)
    site = geodetic_to_ecef(math.radians(lat), math.radians(lon), h)
    e, n, u = ecef_to_enu(site, math.radians(55.93), math.radians(37.52), 190.0)
    assert math.hypot(e, n) == pytest.approx(300.0, abs=1e-6)
    assert math.degrees(math.atan2(e, n)) == pytest.approx(140.0, abs=1e-9)


def test_a_folder_without_a_document_is_a_one_line_error(tmp_path):
    from sitl.app.report import ReportError, write_report

    with pytest.raises(ReportError, match="no result.json or report.json"):
        write_report(tmp_path)
