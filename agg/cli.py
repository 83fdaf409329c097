"""The ``agg`` console script.

Each sub-command lives in its own module under ``agg/commands/`` and exposes
``add_parser(subparsers)``, which registers the sub-command and sets ``func`` (a callable taking the parsed
``argparse.Namespace`` and returning an exit code). Modules are discovered, so adding a command touches no
shared file. Commands of other packages (``agg serve`` from ``service``, ``agg worker`` from ``worker``) come
through the entry-point group ``agg.commands`` (pyproject.toml): each points at a ``register(subparsers)``, so the
engine imports nothing from the service.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from agg import __version__


def build_parser() -> argparse.ArgumentParser:
    import agg.commands as commands

    parser = argparse.ArgumentParser(prog="agg", description="AGG: 4D Gaussian scene graphs from driving videos.")
    parser.add_argument("--version", action="version", version=f"agg {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"agg.commands.{info.name}")
        module.add_parser(sub)
    from importlib.metadata import entry_points

    for ep in sorted(entry_points(group="agg.commands"), key=lambda e: e.name):
        try:
            register = ep.load()
        except ImportError as exc:  # a plugin whose extra dependencies are missing: say so, keep the rest
            sub.add_parser(ep.name, help=f"(unavailable: {exc})")
            continue
        register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
