"""``mosiv parity``: the backend-parity suite over installed simulators, as a table."""

from __future__ import annotations

import json


def add_parser(sub) -> None:
    p = sub.add_parser(
        "parity", help="check simulator backends against the reference laws and each other"
    )
    p.add_argument(
        "--backends", help="comma-separated simulators (default: every installed simulator)"
    )
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    p.add_argument("--laws", help="comma-separated material families (default: all six)")
    p.add_argument("--no-gradients", action="store_true", help="skip the gradient comparison")
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=run)


def run(args) -> int:
    from mosiv_framework.laws import FAMILIES
    from mosiv_framework.registry import get_registry
    from mosiv_framework.testing.parity import run_parity

    registry = get_registry()
    names = args.backends.split(",") if args.backends else registry.names("simulator")
    for name in names:
        registry.get("simulator", name)  # unknown names fail here, listing the valid ones

    def maker(name):
        return lambda **options: registry.create(
            "simulator", name, {**options, "device": args.device}
        )

    laws = tuple(args.laws.split(",")) if args.laws else FAMILIES
    report = run_parity({n: maker(n) for n in names}, laws=laws, gradients=not args.no_gradients)
    if args.json:
        print(json.dumps({"passed": report.passed, "results": report.as_dicts()}, indent=2))
    else:
        print(report.table())
        print("parity: " + ("PASS" if report.passed else f"FAIL ({len(report.failures)} checks)"))
    return 0 if report.passed else 1
