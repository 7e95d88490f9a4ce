"""Checks of what the commands write, shared by the CLI tests."""
import json


def strict_json(text: str):
    """json.loads that fails on NaN / Infinity (result.json must be strict JSON)."""
    def no_constants(name):
        raise AssertionError(f"non-strict JSON constant {name}")

    return json.loads(text, parse_constant=no_constants)


def is_png(path) -> bool:
    data = path.read_bytes()
    return len(data) > 1000 and data[:8] == b"\x89PNG\r\n\x1a\n"
