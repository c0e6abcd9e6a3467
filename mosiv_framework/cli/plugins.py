"""``mosiv plugins``: installed distributions, their components, and plugins that failed to load."""

from __future__ import annotations

import json


def add_parser(sub) -> None:
    p = sub.add_parser("plugins", help="list installed plugins and the components they provide")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(handler=run)


def plugins_report() -> dict:
    from mosiv_framework.registry import get_registry

    registry = get_registry()
    return {
        "plugins": [
            {
                "name": info.name,
                "distribution": info.distribution,
                "version": info.version,
                "module": info.module,
                "components": [
                    {"kind": c.kind, "name": c.name, "description": c.description}
                    for c in info.components
                ],
            }
            for info in registry.plugins.values()
        ],
        "broken": [
            {"name": b.name, "distribution": b.distribution, "error": b.error}
            for b in registry.broken
        ],
        "disabled": list(registry.disabled),
        "conflicts": [c.message() for c in registry.conflicts],
    }


def run(args) -> int:
    report = plugins_report()
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    for plugin in report["plugins"]:
        print(f"{plugin['distribution']} {plugin['version']}  (plugin {plugin['name']!r})")
        for c in plugin["components"]:
            print(f"    {c['kind']:<17} {c['name']:<20} {c['description']}")
    for b in report["broken"]:
        print(f"BROKEN {b['distribution']} (plugin {b['name']!r}): {b['error']}")
    for name in report["disabled"]:
        print(f"disabled: {name}")
    for message in report["conflicts"]:
        print(f"CONFLICT: {message}")
    return 0
