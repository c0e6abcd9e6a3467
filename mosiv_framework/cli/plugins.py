"""``mosiv plugins``: installed distributions, their components, and plugins that failed to load.

``mosiv plugins --options NAME`` prints one component's option schema instead: every option
with its type, default and doc (``--json``: the same as JSON).
"""

from __future__ import annotations

import json
import textwrap


def add_parser(sub) -> None:
    p = sub.add_parser("plugins", help="list installed plugins and the components they provide")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument(
        "--options",
        metavar="NAME",
        help="show the options of one component (KIND:NAME, or a NAME only one kind has): "
        "type, default and description of each",
    )
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


def options_report(spec: str) -> dict:
    """The component ``spec`` names and its option schema (see ``registry.optiondoc``)."""
    from mosiv_framework.registry import get_registry
    from mosiv_framework.registry.optiondoc import jsonable, option_schema

    component = get_registry().find(spec)
    schema = option_schema(component.options) if component.options is not None else []
    for entry in schema:
        if "default" in entry:
            entry["default"] = jsonable(entry["default"])
    return {
        "kind": component.kind,
        "name": component.name,
        "distribution": component.distribution,
        "description": component.description,
        "options": schema,
    }


def _print_options(report: dict) -> None:
    print(
        f"{report['kind']} {report['name']!r} ({report['distribution']}): {report['description']}"
    )
    if not report["options"]:
        print("    takes no options")
    for entry in report["options"]:
        default = "required" if entry.get("required") else f"default {entry['default']!r}"
        print(f"    {entry['name']}: {entry['type']}, {default}")
        if entry["doc"]:
            for line in textwrap.wrap(entry["doc"], width=88):
                print(f"        {line}")


def run(args) -> int:
    if args.options:
        report = options_report(args.options)
        if args.json:
            print(json.dumps(report, indent=2))
        else:
            _print_options(report)
        return 0
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
