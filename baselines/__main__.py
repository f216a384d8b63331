"""``python -m baselines``: the registered methods as a Markdown table (:func:`baselines.methods.markdown_table`);
``python -m baselines register A B --method NAME``: register two point-cloud files (:mod:`baselines.register_cli`)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from baselines.methods import markdown_table
from baselines.register_cli import add_parser
from src.utils.errors import exit_code_of


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m baselines", description=__doc__)
    sub = parser.add_subparsers(dest="command")
    sub.add_parser("list", help="the registered methods as a Markdown table (the default)")
    add_parser(sub)
    args = parser.parse_args(argv)
    if args.command in (None, "list"):
        sys.stdout.write(markdown_table())
        return 0
    return exit_code_of(lambda: args.action(args))


if __name__ == "__main__":
    sys.exit(main())
