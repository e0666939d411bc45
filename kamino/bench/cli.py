"""``kamino bench``: ``kamino bench ARGS`` runs the throughput benchmark (:mod:`kamino.bench.throughput`);
``kamino bench NAME ARGS`` runs the benchmark module ``NAME`` of :data:`kamino.bench.MODULES`."""

from __future__ import annotations

import importlib
import sys

from kamino.bench import MODULES


def main(argv: list[str] | None = None) -> int:
    """Run ``kamino bench [NAME] ARGS``; the exit status of the benchmark (argparse exits 2 on a bad option)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    name, prog = "throughput", "kamino bench"
    if argv and argv[0] in MODULES:
        name, prog, argv = argv[0], f"kamino bench {argv[0]}", argv[1:]
    elif argv and not argv[0].startswith("-"):
        print(f"kamino bench: unknown benchmark {argv[0]!r}; NAME is one of {', '.join(MODULES)}, or none for "
              "throughput (kamino bench --help)", file=sys.stderr)
        return 2
    module = importlib.import_module(f"kamino.bench.{name}")
    return int(module.main(argv, prog=prog) or 0)


if __name__ == "__main__":
    raise SystemExit(main())
