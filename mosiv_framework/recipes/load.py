"""Loading, overriding and validating recipes.

``load_recipe`` returns the fully resolved recipe (defaults and component options filled in) or
raises ConfigError listing *every* problem at once, so a user fixes a recipe in one pass before
anything runs.
"""

from __future__ import annotations

import dataclasses
import io
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from mosiv_framework.errors import ConfigError
from mosiv_framework.recipes.cell_size import KEY as CELL_SIZE
from mosiv_framework.recipes.cell_size import take_cell_size
from mosiv_framework.recipes.interpolation import resolve_recipe, syntax_problems
from mosiv_framework.recipes.rules import cross_section_findings
from mosiv_framework.recipes.schema import COMPONENT_SECTIONS, MULTI_COMPONENT_SECTIONS, Recipe
from mosiv_framework.recipes.terms import check_physics_terms
from mosiv_framework.registry import Registry, get_registry, validate_options


def read_recipe_file(path: str | Path, overrides: Sequence[str] = ()) -> dict[str, Any]:
    """The recipe as written plus ``key=value`` overrides, interpolations resolved, as plain
    containers (no schema yet). Raises ConfigError naming the file, or every bad override and
    interpolation with its key (see ``mosiv_framework.recipes.interpolation``)."""
    user = _load_yaml(Path(path))
    problems = []
    for item in overrides:
        if "=" not in item:
            problems.append(f"override {item!r} is not of the form key=value")
            continue
        try:
            user = OmegaConf.merge(user, OmegaConf.from_dotlist([item]))
        except (OmegaConfBaseException, yaml.YAMLError) as exc:
            problems.append(f"override {item!r}: {_first_line(exc)}")
    if problems:
        raise ConfigError(problems)
    resolved, problems = resolve_recipe(user)
    if problems:
        raise ConfigError([f"{path}: {p}" for p in problems])
    return resolved


def _load_yaml(path: Path) -> DictConfig:
    """The file's top-level mapping; ConfigError naming the file for anything else."""
    if not path.is_file():
        what = "is a folder, not" if path.is_dir() else "does not exist; give"
        raise ConfigError(f"recipe file {str(path)!r} {what} a recipe YAML file")
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"{path}: not a text file (byte {exc.start} is not UTF-8); a recipe is YAML text"
        ) from exc
    try:
        # the node tree gives the top-level type without building anything; OmegaConf's own
        # loader then rejects duplicate keys and caps alias expansion
        node = yaml.compose(text, Loader=yaml.SafeLoader)
        data = OmegaConf.load(io.StringIO(text)) if isinstance(node, yaml.MappingNode) else None
    except yaml.YAMLError as exc:  # yaml errors carry the line and column
        where = str(exc).replace('"<unicode string>"', str(path))  # parsed from a string
        raise ConfigError(f"{path}: not valid YAML: {where}") from exc
    except OmegaConfBaseException as exc:  # a bad interpolation, a key of an odd type
        # the YAML itself parsed: name the keys whose strings are not valid interpolations
        named = syntax_problems(yaml.safe_load(text))
        first = _first_line(exc).replace('"<file>"', str(path))  # parsed from a stream
        raise ConfigError([f"{path}: {p}" for p in named] or f"{path}: {first}") from exc
    if node is None or (isinstance(node, yaml.ScalarNode) and node.tag.endswith(":null")):
        raise ConfigError(
            f"{path}: the recipe file is empty (no sections); a recipe names at least its scene "
            "(scene.path, or scene.source to generate it), as recipes/quickstart.yaml does"
        )
    if not isinstance(data, DictConfig):
        kind = "list" if isinstance(node, yaml.SequenceNode) else "single value"
        raise ConfigError(
            f"{path}: a recipe is a mapping of sections (scene:, simulator:, identify:, ...), "
            f"got a YAML {kind}"
        )
    return data


def _first_line(exc: BaseException) -> str:
    lines = str(exc).strip().splitlines()
    return lines[0] if lines else type(exc).__name__


def validate_recipe(
    raw: Mapping[str, Any], registry: Registry, *, warnings: list[str] | None = None
) -> tuple[dict[str, Any], list[str]]:
    """Check a raw recipe against the schema, the registry and the rules between sections.

    Args:
        raw: the recipe as plain containers (``read_recipe_file``).
        registry: the component registry.
        warnings: if given, receives what is valid but worth saying (e.g. where the simulator
            settings cap a stiffness, see ``mosiv_framework.recipes.stiffness``).
    Returns:
        (resolved recipe with defaults filled in, every problem found).
    """
    problems: list[str] = []
    resolved: dict[str, Any] = {}
    sections = {f.name: f for f in dataclasses.fields(Recipe)}
    for key in raw:
        if key not in sections:
            problems.append(
                f"unknown recipe section {key!r}; valid sections: {', '.join(sections)}"
            )
    defaults = Recipe()
    cell_notes: list[str] = []
    for name, _fld in sections.items():
        value = raw.get(name, getattr(defaults, name))
        if name in COMPONENT_SECTIONS:
            cell_size = None
            if name == "simulator" and isinstance(value, Mapping):
                value = dict(value)
                has_grid = _has_option(registry, "simulator", value.get("name"), "grid")
                cell_size = take_cell_size(name, value, has_grid, problems, cell_notes)
            resolved[name] = _check_component(
                name, COMPONENT_SECTIONS[name], value, registry, problems
            )
            if cell_size is not None:  # the run turns it into the grid of its scene
                resolved[name].update({CELL_SIZE: cell_size, "grid": None})
        elif name == "physics_terms":
            resolved[name] = check_physics_terms(value, registry, problems)
        elif name in MULTI_COMPONENT_SECTIONS:
            resolved[name] = _check_components(
                name, MULTI_COMPONENT_SECTIONS[name], value, registry, problems
            )
        else:
            resolved[name] = _check_section(name, type(getattr(defaults, name)), value, problems)
    source = (resolved.get("scene") or {}).get("source")
    if source is not None:
        resolved["scene"]["source"] = _check_component(
            "scene.source", "scene_source", source, registry, problems
        )
    if not problems:  # the rules between sections assume each section is sound
        more, notes = cross_section_findings(resolved, registry)
        problems.extend(more)
        if warnings is not None:
            warnings.extend(notes)
    if warnings is not None:
        warnings.extend(cell_notes)
    return resolved, problems


def _has_option(registry: Registry, kind: str, name: Any, option: str) -> bool:
    """Whether the registered component ``name`` of ``kind`` takes ``option`` (True when the
    name is not registered: that problem is reported on its own)."""
    try:
        component = registry.get(kind, name)
    except (ConfigError, TypeError):
        return True
    return option in getattr(component.options, "__dataclass_fields__", {})


def check_recipe(
    path: str | Path, overrides: Sequence[str] = (), *, registry: Registry | None = None
) -> tuple[DictConfig, list[str]]:
    """``load_recipe`` that also returns the warnings (for ``mosiv recipe validate``)."""
    raw = read_recipe_file(path, overrides)
    warnings: list[str] = []
    resolved, problems = validate_recipe(raw, registry or get_registry(), warnings=warnings)
    if problems:
        raise ConfigError([_where(p, path, overrides) for p in problems])
    return OmegaConf.create(resolved), warnings


def _where(problem: str, path: str | Path, overrides: Sequence[str]) -> str:
    """``problem`` prefixed with where it comes from: the command-line override whose key it
    names (a typo there is not the file's), else the recipe file. An override the problem names
    by its whole key wins over one whose option a plugin names (``_names_option``)."""
    keys = [(item, item.partition("=")[0].strip()) for item in overrides]
    for names in (_names_key, _names_option):
        for item, key in keys:
            if key and names(problem, key):
                return f"override {item!r}: {problem}"
    return f"{path}: {problem}"


def _names_key(problem: str, key: str) -> bool:
    """Whether ``problem`` names the dotted ``key`` whole (not the tail of a longer one: dt=
    inside simulator.dt=), or the unknown section it starts with."""
    section = re.escape(key.split(".")[0])
    named = rf"(?<![\w.]){re.escape(key)}[;=]|unknown recipe section '{section}'"
    return problem.startswith(f"{key}: ") or re.search(named, problem) is not None


def _names_option(problem: str, key: str) -> bool:
    """Whether ``problem`` is about the option that the override ``key`` sets where a plugin
    checks its options: the problem starts with a dotted prefix of the key ("scene.source: ",
    "losses.chamfer: ") and names the key's next part the way plugins do ("option
    substeps=0", "has no option 'foo'", "voxel_size must ..."); the override's value replaced
    the file's, so a problem with it is the override's."""
    parts = key.split(".")
    for cut in range(len(parts) - 1, 0, -1):  # the longest prefix the problem starts with
        if problem.startswith(".".join(parts[:cut]) + ": "):
            leaf = re.escape(parts[cut])
            said = re.split(r"valid (?:options|values|names)", problem)[0]  # not the lists
            forms = rf"(?<!\w){leaf}(?:=| must )|option '{leaf}'"
            return re.search(forms, said) is not None
    return False


def load_recipe(
    path: str | Path, overrides: Sequence[str] = (), *, registry: Registry | None = None
) -> DictConfig:
    """Read, override and validate a recipe; raise ConfigError with every problem found.
    Warnings are left to the pipeline, which checks the stiffness caps against the scene it
    reads (``mosiv_framework.recipes.stiffness.check_stiffness``)."""
    return check_recipe(path, overrides, registry=registry)[0]


def _check_section(name: str, schema: type, value: Any, problems: list[str]) -> dict[str, Any]:
    """A plain dataclass section: unknown keys and wrongly typed values."""
    if not isinstance(value, Mapping):
        if dataclasses.is_dataclass(value):
            return dataclasses.asdict(value)
        problems.append(f"section {name!r} must be a mapping, got {value!r}")
        return {}
    valid = [f.name for f in dataclasses.fields(schema)]
    merged = OmegaConf.structured(schema)
    for key, item in value.items():
        if key not in valid:
            problems.append(f"unknown key {name}.{key}; valid keys of {name}: {', '.join(valid)}")
            continue
        try:
            merged = OmegaConf.merge(merged, {key: item})
        except OmegaConfBaseException as exc:
            first = str(exc).strip().splitlines()[0]
            problems.append(f"{name}.{key}={item!r}: {first}")
    resolved = OmegaConf.to_container(merged, resolve=True)
    check_values = getattr(schema, "value_problems", None)  # range and choice checks
    if check_values is not None:
        problems.extend(check_values(resolved))
    return resolved  # type: ignore[return-value]


def _check_component(
    where: str, kind: str, value: Any, registry: Registry, problems: list[str]
) -> dict[str, Any]:
    """A ``{name: ..., option: ...}`` section: registered name and the component's options."""
    if not isinstance(value, Mapping) or "name" not in value:
        problems.append(
            f"{where} must be a mapping with a 'name' key; valid {kind} names: "
            f"{', '.join(registry.names(kind)) or 'none installed'}"
        )
        return dict(value) if isinstance(value, Mapping) else {}
    options = {k: v for k, v in value.items() if k != "name"}
    try:
        component = registry.get(kind, value["name"])
    except ConfigError as exc:
        problems.extend(f"{where}.name: {p}" for p in exc.problems)
        return dict(value)
    try:
        return {"name": value["name"], **validate_options(component, options)}
    except ConfigError as exc:
        problems.extend(f"{where}: {p}" for p in exc.problems)
        return dict(value)


def _check_components(
    where: str, kind: str, value: Any, registry: Registry, problems: list[str]
) -> dict[str, Any]:
    """A mapping of component name -> options (the ``losses`` section)."""
    if not isinstance(value, Mapping):
        problems.append(f"{where} must map {kind} names to their options, got {value!r}")
        return {}
    resolved = {}
    for name, options in value.items():
        options = {} if options is None else options
        if not isinstance(options, Mapping):
            problems.append(f"{where}.{name} must be a mapping of options, got {options!r}")
            continue
        checked = _check_component(
            f"{where}.{name}", kind, {"name": name, **options}, registry, problems
        )
        checked.pop("name", None)
        resolved[name] = checked
    return resolved
