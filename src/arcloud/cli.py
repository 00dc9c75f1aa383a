"""The `arcloud` command line: demo, eval, serve, worker, replay, frames, keys, export, maps, models."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from arcloud.accuracy.cli import add_eval_commands
from arcloud.allocator import keep_freed_memory
from arcloud.argtypes import PARAMS_HELP, params_overrides, parse_users, positive_int
from arcloud.tools.export_cli import add_export_command
from arcloud.tools.frames_cli import add_frames_commands
from arcloud.tools.keys_cli import add_keys_commands
from arcloud.tools.maps_cli import add_maps_commands
from arcloud.tools.models_cli import add_models_commands
from arcloud.tools.service_cli import add_service_commands


def add_demo_command(subparsers: argparse._SubParsersAction) -> None:
    demo = subparsers.add_parser(
        "demo",
        help="reproduce the paper's Table 1 on a simulated room (one process, no server)",
        description="Centralized and distributed (K users) runs on one simulated room; prints Table 1 and "
        "writes results.json and top-down pictures.",
    )
    demo.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder (default: out/demo)")
    demo.add_argument("--seed", type=int, default=0, help="room, walk and detector-fault seed (default 0)")
    demo.add_argument("--frames", type=positive_int, default=300, help="frames in the walk (default 300)")
    demo.add_argument("--runs", type=positive_int, default=3, help="Monte-Carlo runs per K (default 3)")
    demo.add_argument("--users", type=parse_users, default=(10, 50, 100), help="K values (default 10,50,100)")
    demo.add_argument("--workers", type=positive_int, default=4, help="worker threads for distributed runs")
    demo.add_argument("--params", metavar="JSON", type=params_overrides, help=PARAMS_HELP)
    demo.add_argument("--no-progress", action="store_true", help="no progress bar")
    demo.set_defaults(handler=run_demo_command)


def run_demo_command(args: argparse.Namespace) -> int:
    from arcloud.argtypes import params_given
    from arcloud.demo import format_table1, run_demo

    params = params_given(args.params)
    results = run_demo(
        args.out,
        seed=args.seed,
        n_frames=args.frames,
        runs=args.runs,
        users=args.users,
        workers=args.workers,
        params=params,
        show_progress=not args.no_progress,
    )
    print(format_table1(results))
    print(
        f"\nwrote {args.out / 'results.json'} and {', '.join(results['pictures'].values())} in {args.out} "
        f"({results['seconds']['total']:.0f} s)"
    )
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="arcloud", description="Multi-user 3D object detection in an AR cloud.")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-v info, -vv debug)")
    subparsers = parser.add_subparsers(dest="command", required=True)
    add_demo_command(subparsers)
    add_eval_commands(subparsers)
    add_service_commands(subparsers)
    add_export_command(subparsers)
    add_frames_commands(subparsers)
    add_keys_commands(subparsers)
    add_maps_commands(subparsers)
    add_models_commands(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = [logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    keep_freed_memory()  # every command processes frame after frame
    try:
        return int(args.handler(args) or 0)
    except KeyboardInterrupt:
        return 130
    except Exception as exc:  # the CLI's edge: a clear message, not a traceback, for known errors
        import httpx

        from arcloud.errors import ArcloudError

        if isinstance(exc, ArcloudError):
            print(f"arcloud: error: {exc}", file=sys.stderr)
            return 2
        if isinstance(exc, httpx.TransportError):  # the SDK's retries spent: no service there, or it stopped answering
            try:
                where = f" at {exc.request.url.copy_with(query=None, username=None, password=None)}"  # no credentials
            except RuntimeError:  # no request attached
                where = ""
            print(
                f"arcloud: error: could not reach the service{where}: {exc or type(exc).__name__} (running? --url)",
                file=sys.stderr,
            )
            return 2
        raise


if __name__ == "__main__":
    sys.exit(main())
