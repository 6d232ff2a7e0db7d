"""
Benchmarks.

``python -m spacerobot_planner.bench {cspace,field,plan,scenes,latency,chain,reaction,redundant,startup,cancel,
envelope,peers,coldstart,all,aims} [options]``.

``all`` runs each benchmark in turn; ``aims`` runs those that issue 19's aims name and prints
every aim against its limit, measured in that one run (:mod:`.aims`).

Every benchmark warms the JIT first, prints a readable table, and one JSON object per
line (``stage``, ``grid``, ``solver``, ``seconds``, ...) so runs can be compared.
Timings are never asserted in tests.
"""

from __future__ import annotations

import importlib
import sys

BENCHES = ("cspace", "field", "plan", "scenes", "latency", "chain", "reaction", "redundant", "startup", "cancel",
           "envelope", "peers", "coldstart")
#: run by name only, not by ``all`` (it runs benchmarks of ``BENCHES`` itself)
SUMMARIES = ("aims",)


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__)
        return 0 if argv else 1
    name, rest = argv[0], argv[1:]
    if name == "all" and any(a in ("-h", "--help") for a in rest):     # not the first benchmark's help
        print(f"bench all [ARGS]: runs {', '.join(BENCHES)} in turn, each with ARGS, stopping at the first that "
              f"fails; bench NAME --help: one benchmark's options")
        return 0
    names = BENCHES if name == "all" else (name,)
    for n in names:
        if n not in BENCHES + SUMMARIES:
            print(f"bench: unknown benchmark '{n}' (choose from {', '.join(BENCHES + SUMMARIES)}, all)",
                  file=sys.stderr)
            return 1
        try:
            mod = importlib.import_module(f"spacerobot_planner.bench.{n}")
        except ImportError as e:
            print(f"bench: '{n}' is not available: {e}", file=sys.stderr)
            return 1
        rc = mod.main(rest)
        if rc:
            return rc
    return 0


if __name__ == "__main__":
    sys.exit(main())
