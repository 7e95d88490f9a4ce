"""`skyfuse fault set LINK SPEC...` and `skyfuse fault list`: change / show a running live
run's network faults through its control key (sitl.netfault.control).

    skyfuse fault set mav:1 loss=10% delay=100ms~20ms --out out/demo
    skyfuse fault set zenoh:gs partition=120-150 --zenoh tcp/127.0.0.1:7447 --run demo
    skyfuse fault set bus:*/uav/2/** none --out out/run
    skyfuse fault list --out out/demo

The router and the run id come from OUT/run.json (written by the launcher), or from
--zenoh / --run. Exit status: 0 when the launcher acknowledged the change, 2 for a bad spec
or an unknown link (checked here first, then by the launcher) or other usage errors, 1 when
no launcher answers within --timeout seconds.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from sitl.app.live_faults import (  # the parser (light)
    DEFAULT_OUTS,
    FaultListOptions,
    FaultSetOptions,
    add_fault_args,
)

from sitl.app.args import UsageError, options_of

EXIT_OK, EXIT_NO_ANSWER, EXIT_USAGE = 0, 1, 2




def _target(args: FaultListOptions) -> tuple[list[str], str, dict]:
    """(router endpoints, run id, run.json or {})."""
    doc: dict = {}
    path = None
    if args.out is not None:
        path = Path(args.out) / "run.json"
        if not path.is_file() and not args.zenoh:
            raise UsageError(f"fault: {str(path)!r}: no such file (is a live run writing to {str(args.out)!r}?)")
    elif not args.zenoh:
        found = [Path(d) / "run.json" for d in DEFAULT_OUTS if (Path(d) / "run.json").is_file()]
        if not found:
            raise UsageError("fault: no run found: give --out DIR (the run's output directory) or --zenoh tcp/HOST:PORT")
        path = max(found, key=lambda p: p.stat().st_mtime)
    if path is not None and path.is_file():
        try:
            doc = json.loads(path.read_text())
            if not isinstance(doc, dict):
                raise ValueError("not an object")
        except (OSError, ValueError) as e:
            raise UsageError(f"fault: {str(path)!r}: not a run.json: {e}") from None
    endpoints = list(args.zenoh) if args.zenoh else list(doc.get("zenoh") or [])
    if not endpoints:
        raise UsageError(f"fault: {str(path)!r} names no Zenoh router; give --zenoh tcp/HOST:PORT")
    from sitl.scenario import ScenarioError, zenoh_endpoint
    for e in endpoints:
        try:
            zenoh_endpoint("--zenoh", e)
        except ScenarioError as err:
            raise UsageError(str(err).replace("scenario: ", "fault: ")) from None
    run_id = args.run or doc.get("run_id") or "demo"
    from sitl.bus import is_valid_id
    if not is_valid_id(run_id):
        raise UsageError(f"fault: --run: expected 1..64 characters of [A-Za-z0-9_.-], got {run_id!r}")
    return endpoints, run_id, doc


def _request(endpoints, run_id, link, spec, timeout_s) -> tuple[bool, str] | None:
    """Publish one FaultControl and wait for the launcher's answer: (ok, text) or None."""
    import os

    from sitl.bus import ZenohTransport
    from sitl.bus.schema import FaultControl
    from sitl.bus.zenoh_transport import ZenohTransportError
    from sitl.netfault.control import ERROR_PREFIX, ack_key, control_key
    seq = (os.getpid() << 20 | int(time.time() * 1000) & 0xFFFFF) % (1 << 62)
    answers = []
    try:
        bus = ZenohTransport(connect=endpoints, mode="client")
    except ZenohTransportError as e:
        print(f"fault: {' '.join(str(e).split())}", file=sys.stderr)
        return None
    try:
        bus.subscribe(ack_key(run_id), lambda k, m: answers.append(m) if m.seq == seq else None)
        t_end = time.monotonic() + timeout_s
        if not bus.wait_for_subscribers(control_key(run_id), max(0.0, timeout_s)):
            return None
        req = FaultControl(t_gps_s=0.0, source_id="cli", seq=seq, link=link, spec=spec)
        next_send = 0.0
        while time.monotonic() < t_end:
            # until answered, the same request again every 0.5 s: the answer may have gone out before
            # this session's subscription reached the router; the launcher applies a (source, seq) once
            if time.monotonic() >= next_send:
                bus.publish(control_key(run_id), req)
                next_send = time.monotonic() + 0.5
            bus.drain()
            if answers:
                text = answers[0].spec
                if text.startswith(ERROR_PREFIX):
                    return False, text[len(ERROR_PREFIX):]
                return True, text
            time.sleep(0.01)
        return None
    finally:
        bus.close()


def fault_main(args) -> int:
    from sitl.netfault import FaultSpecError, parse_spec
    from sitl.netfault.control import LIST_LINK, canonical_link
    command = args.fault_command
    args = options_of(FaultSetOptions if command == "set" else FaultListOptions, args)  # --timeout: checked there
    if command == "set":
        spec = " ".join(args.spec)
        try:
            link = canonical_link(args.link)
        except ValueError as e:
            raise UsageError(f"fault: {e}") from None
        try:
            parsed = parse_spec(spec)
        except FaultSpecError as e:
            raise UsageError(" ".join(str(e).split())) from None
        if link.startswith("zenoh:"):  # a byte stream: delay, rate and partitions only
            from sitl.netfault.tcp_proxy import stream_spec
            try:
                stream_spec(parsed, link)
            except ValueError as e:
                raise UsageError(f"fault: {' '.join(str(e).split())}") from None
    else:
        link, spec = LIST_LINK, ""
    endpoints, run_id, doc = _target(args)
    if doc.get("finished"):
        print(f"fault: the run {run_id!r} has ended (run.json says finished)", file=sys.stderr)
        return EXIT_NO_ANSWER
    if command == "set" and doc.get("links") is not None and not link.startswith("bus:"):
        known = set(doc["links"])
        if link not in known and not ({f"{link}:up", f"{link}:down"} <= known):
            raise UsageError(f"fault: unknown link {link!r} in run {run_id!r} (links: {', '.join(sorted(known)) or 'none'})")
    ans = _request(endpoints, run_id, link, spec, args.timeout)
    if ans is None:
        print(f"fault: no launcher of run {run_id!r} answered at {', '.join(endpoints)} within {args.timeout:g} s",
              file=sys.stderr)
        return EXIT_NO_ANSWER
    ok, text = ans
    if not ok:
        raise UsageError(f"fault: the launcher refused it: {text}")
    if command == "list":
        try:
            cur = json.loads(text)
        except ValueError:
            cur = {}
        for name in sorted(cur):
            print(f"{name:28s} {cur[name]}")
        return EXIT_OK
    print(f"{link} = {text}")
    return EXIT_OK


def main(argv=None) -> int:
    """Stand-alone entry (`python -m sitl.app.fault_cli set LINK SPEC...`), the same as `skyfuse fault`."""
    from sitl.app.args import UsageError, Parser as _Parser
    p = _Parser(prog="skyfuse fault", description=__doc__.split("\n\n")[0])
    add_fault_args(p)
    try:
        return fault_main(p.parse_args(argv))
    except UsageError as e:
        print(f"error: {e}", file=sys.stderr)
        return EXIT_USAGE


if __name__ == "__main__":
    sys.exit(main())
