"""What every experiment command shares: strict JSON, figure saving, progress, the output
directory check, and loading the vehicle / ground-station packages by module name (sitl
never imports them statically: see ARCHITECTURE.md, "Dependency direction")."""
from __future__ import annotations

import importlib
import math
import os
import sys
from pathlib import Path

import numpy as np


def strict(v):
    """A JSON-able copy: numpy to Python, inf / nan to None (json.dump(allow_nan=False) works)."""
    if isinstance(v, dict):
        return {str(k): strict(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [strict(x) for x in v]
    if isinstance(v, np.ndarray):
        return strict(v.tolist())
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(v) if math.isfinite(v) else None
    return v


def save_figure(fig, path: Path) -> Path:
    import matplotlib.pyplot as plt

    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def progress_printer(quiet: bool):
    """None when quiet, else a function printing one progress line to stderr."""
    if quiet:
        return None
    return lambda msg: print(msg, file=sys.stderr, flush=True)


def prepare_out(out: Path) -> Path:
    """Create the output directory; a usage error (exit 2, one line) if it cannot be written."""
    from sitl.cli import UsageError

    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"cannot create output directory {str(out)!r}: {exc.strerror}") from None
    if not out.is_dir() or not os.access(out, os.W_OK | os.X_OK):
        raise UsageError(f"output directory {str(out)!r} is not writable")
    return out


def component(module: str):
    """A vehicles.* or ground_station.* module, loaded by name at run time."""
    return importlib.import_module(module)
