"""A component's option schema for people: every field with its type, default and doc.

Per-field docs come from where the code base writes them, first found wins:
``field(metadata={"doc": ...})`` (or ``"help"``); a ``#:`` comment block right above the field
in the class body; an entry of the class docstring written ``name: text`` or
``name (unit): text`` (several names may share one text: ``a, b: text``), as in
``mosiv_framework.losses.ChamferOptions`` or ``mosiv_framework.simulation.MPMOptions``. Base
classes are searched too, so a backend's options subclass inherits the docs of the shared ones.
"""

from __future__ import annotations

import dataclasses
import inspect
import re
import typing
from typing import Any

_NAME = r"[A-Za-z_][A-Za-z0-9_]*"
_UNIT = r"\s*\([^()\n]*\)"
_SEP = r"\s*[,/]\s*"  # "a, b: text" and "a / b: text" document a and b at once
# an entry's head: names (each with an optional unit) then a colon, at the start of a line or
# after the "; " or ". " that ends the entry before it
_ENTRY = re.compile(
    rf"(?:^|(?<=[;.])[ \t]+|\n[ \t]*)(?P<head>{_NAME}(?:{_UNIT})?(?:{_SEP}{_NAME}(?:{_UNIT})?)*):"
    r"(?=\s)"
)
_HEAD_NAME = re.compile(rf"({_NAME})(?:\s*\(([^()\n]*)\))?")
# a section heading inside a docstring ("Training (paper eq. 2, ``train.py``):") ends an entry
_HEADING = re.compile(r"\n[ \t]*[A-Z][^\n:;]*:[ \t]*$")


def option_schema(options: type) -> list[dict[str, Any]]:
    """One entry per field of the options dataclass ``options``: name, type, default
    (``required`` when it has none) and doc (empty when nowhere written)."""
    try:
        hints = typing.get_type_hints(options)
    except Exception:  # an annotation that does not evaluate here: show it as written
        hints = {}
    docs = field_docs(options)
    out = []
    for f in dataclasses.fields(options):
        entry: dict[str, Any] = {"name": f.name, "type": _type_text(hints.get(f.name, f.type))}
        if f.default is not dataclasses.MISSING:
            entry["default"] = f.default
        elif f.default_factory is not dataclasses.MISSING:
            entry["default"] = f.default_factory()
        else:
            entry["required"] = True
        entry["doc"] = docs.get(f.name, "")
        out.append(entry)
    return out


def field_docs(options: type) -> dict[str, str]:
    """Field name -> doc text, from metadata, ``#:`` comments and docstrings (see module doc)."""
    names = {f.name for f in dataclasses.fields(options)}
    docs = {
        f.name: str(f.metadata.get("doc") or f.metadata.get("help"))
        for f in dataclasses.fields(options)
        if f.metadata.get("doc") or f.metadata.get("help")
    }
    for cls in options.__mro__:
        if cls is object or not dataclasses.is_dataclass(cls):
            continue
        for source in (_comment_docs(cls), _docstring_docs(cls, names)):
            for name, text in source.items():
                if name in names and name not in docs:
                    docs[name] = text
    return docs


def _docstring_docs(cls: type, names: set[str]) -> dict[str, str]:
    doc = cls.__dict__.get("__doc__") or ""
    if not doc or doc.startswith(cls.__name__ + "("):  # dataclass's generated signature
        return {}
    doc = inspect.cleandoc(doc)
    out: dict[str, str] = {}
    # only heads naming a field start an entry: "Note: ..." or "e.g. x: ..." inside a text
    # stays part of it
    matches = [
        m
        for m in _ENTRY.finditer(doc)
        if any(name in names for name, _ in _head_names(m.group("head")))
    ]
    for i, match in enumerate(matches):
        end = matches[i + 1].start() if i + 1 < len(matches) else len(doc)
        body = doc[match.end() : end]
        heading = _HEADING.search(body)
        if heading:
            body = body[: heading.start()]
        text = " ".join(body.split()).rstrip(";,. ")
        for name, unit in _head_names(match.group("head")):
            out.setdefault(name, f"({unit}) {text}" if unit else text)
    return out


def _head_names(head: str) -> list[tuple[str, str]]:
    """(name, unit) of each name in an entry's head; a unit may hold "/" or ",": "(1/s)"."""
    return [(m.group(1), m.group(2) or "") for m in _HEAD_NAME.finditer(head)]


def _comment_docs(cls: type) -> dict[str, str]:
    try:
        lines = inspect.getsource(cls).splitlines()
    except (OSError, TypeError):  # defined in a REPL or built at run time
        return {}
    out: dict[str, str] = {}
    pending: list[str] = []
    for line in lines[1:]:
        stripped = line.strip()
        if stripped.startswith("#:"):
            pending.append(stripped[2:].strip())
            continue
        match = re.match(rf"({_NAME})\s*:", stripped)
        if match and pending:
            out[match.group(1)] = " ".join(pending)
        pending = []
    return out


def _type_text(annotation: Any) -> str:
    if isinstance(annotation, str):
        return annotation
    if isinstance(annotation, type) and not typing.get_args(annotation):
        return annotation.__name__
    return str(annotation).replace("typing.", "")


def jsonable(value: Any) -> Any:
    """A default as JSON can carry it: tuples as lists, anything unusual as its repr."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    return repr(value)
