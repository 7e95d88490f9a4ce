"""``python -m sitl.app {run,demo,replay} ...``: the live commands before (and besides) their
registration in `skyfuse` (sitl/app/cli.py)."""
import sys


def main(argv=None) -> int:
    from sitl.app.args import UsageError, Parser as _Parser
    from sitl.app import launcher

    p = _Parser(prog="python -m sitl.app")
    sub = p.add_subparsers(dest="command", required=True)
    launcher.add_run_args(sub.add_parser("run", help="run a scenario live"))
    launcher.add_demo_args(sub.add_parser("demo", help="run the built-in default scenario live"))
    launcher.add_replay_args(sub.add_parser("replay", help="replay a bus log through the ground station"))
    from sitl.app.bench import live as bench_live
    bench_live.add_args(sub.add_parser("bench", help="skyfuse bench live"))
    try:
        args = p.parse_args(argv)
        fn = {"run": launcher.run_main, "demo": launcher.demo_main, "replay": launcher.replay_main,
              "bench": bench_live.main}[args.command]
        return int(fn(args) or 0)
    except UsageError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
