"""``mosiv diagnose-suite OUT``: prove the diagnosis on scenes with effects their files conceal.

For each suite entry a scene is generated through the registry's ``synth`` scene source with a
``conceal`` option (the effect is written to ``gt/effects.json``, nowhere else), the pipeline
runs on it (oracle reconstructor), the run is diagnosed, and only then is ``gt/effects.json``
read to score the diagnosis. Entries: concealed effects at two strengths on mixed material
pairs, controls with nothing concealed, and out-of-library entries whose concealed term is
removed from the screened library (the right answer there is "unexplained").

``--source genesis --split dev|test`` runs the Genesis suite instead (``suite_splits``): scenes
the Genesis engine records, with out-of-library fields no term expresses, in a development split
to choose thresholds on and a test split to score once.
"""

from __future__ import annotations

import json
import logging
import math
import os
import statistics
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

from mosiv_framework.conceal_fields import OUT_OF_LIBRARY_KINDS, library_conflicts
from mosiv_framework.diagnose.diagnosis import diagnose_run
from mosiv_framework.diagnose.formats import FIELD, SCORE_FORMAT, SUITE_FORMAT, file_format
from mosiv_framework.errors import ConfigError
from mosiv_framework.expression import NAME as EXPRESSION
from mosiv_framework.pipeline import run_pipeline
from mosiv_framework.pipeline.run import generate_scene
from mosiv_framework.recipes import load_recipe
from mosiv_framework.scale import Task, run_tasks
from mosiv_framework.scene import read_scene

log = logging.getLogger(__name__)

#: the recipe the suite's scenes run with unless another is given
DEFAULT_RECIPES = {
    True: Path(__file__).resolve().parents[2] / "recipes" / "diagnose_small.yaml",
    False: Path(__file__).resolve().parents[2] / "recipes" / "diagnose_suite.yaml",
}


@dataclass
class Entry:
    """One suite scene: ``conceal`` spec ("" for a control), material pair, seed, and the
    library restriction (``exclude``: comma-separated candidates the diagnosis may not screen)."""

    name: str
    conceal: str = ""
    materials: str = "elastic,elastic"
    seed: int = 0
    exclude: str = ""
    #: further recipe overrides of this entry's run (``key=value``)
    overrides: tuple[str, ...] = ()

    @property
    def kind(self) -> str:
        return self.conceal.split(":", 1)[0] if self.conceal else ""

    @property
    def outside(self) -> bool:
        """Whether the concealed effect is outside the screened library: excluded from it, or
        an out-of-library field (``conceal_fields``)."""
        return bool(self.exclude) or self.kind in OUT_OF_LIBRARY_KINDS


def suite_entries(small: bool) -> list[Entry]:
    """The small suite (CPU, minutes) or the full one (the scores in docs/RESULTS.md)."""
    if small:
        return [
            Entry("wind", "wind:acceleration=2.5,0,0"),
            Entry("linear_drag", "linear_drag:coefficient=2.0", seed=1),
            Entry("control", "", seed=2),
        ]
    pairs = ("elastic,plasticine", "elastic,elastic", "plasticine,sand", "elastic,sand")
    # two strengths per kind: a clear one and a weaker one (SNR decides whether it counts)
    strengths = {
        "linear_drag": ("linear_drag:coefficient=1.0", "linear_drag:coefficient=2.5"),
        "quadratic_drag": ("quadratic_drag:coefficient=1.0", "quadratic_drag:coefficient=2.5"),
        "wind": ("wind:acceleration=1.5,0,0", "wind:acceleration=0,2.5,0"),
        "gravity": ("gravity:acceleration=0,0,-12", "gravity:acceleration=0,0,-7.5"),
        "ground_friction": ("ground_friction:coefficient=0.05", "ground_friction:coefficient=0.12"),
        "ground_restitution": (
            "ground_restitution:coefficient=0.5",
            "ground_restitution:coefficient=0.9",
        ),
        "material_damping": ("material_damping:viscosity=20", "material_damping:viscosity=60"),
        "object_friction": ("object_friction:coefficient=1.2", "object_friction:coefficient=0.0"),
        "plasticity": ("plasticity:yield_stress=3000", "plasticity:yield_stress=8000"),
    }
    # a run identifies table and body friction by default, absorbing a concealed one; these
    # entries run the model a user starts from when they are taken as known (the default 0.3)
    fixed = {
        "ground_friction": ("identify.identify_ground_friction=false",),
        "object_friction": ("identify.identify_friction=false",),
    }
    # concealed plasticity needs a body declared elastic: the pairs that hold exactly one
    elastic_pairs = ("elastic,sand", "elastic,plasticine")
    out, seed = [], 10
    for kind, specs in strengths.items():
        for level, spec in enumerate(specs):
            choices = elastic_pairs if kind == "plasticity" else pairs
            pair = choices[seed % len(choices)]
            out.append(Entry(f"{kind}-{level}", spec, pair, seed, "", fixed.get(kind, ())))
            seed += 1
    for i in range(6):
        out.append(Entry(f"control-{i}", "", pairs[i % len(pairs)], 100 + i))
    # out of library: the concealed kind and every term that can express it exactly are left
    # out of the screened library (a change of gravity is a vertical wind; quadratic drag is
    # close to linear drag over one flight), so nothing left should pass the evidence test
    outside = {
        "quadratic_drag": "linear_drag,quadratic_drag",
        "gravity": "gravity,wind",
        "material_damping": "material_damping",
    }
    for i, (kind, excluded) in enumerate(outside.items()):
        spec = strengths[kind][1]
        out.append(Entry(f"outside-{kind}", spec, pairs[i], 200 + i, exclude=excluded))
    return out


@dataclass
class Score:
    """How the diagnosis did on one entry (errors relative; None where not applicable)."""

    name: str
    concealed: str
    verdict: str
    accepted: str | None
    ranked_first: str | None
    correct: bool
    signal_to_noise: float
    coefficient_error: float | None
    future_reduction: float | None
    extra: dict = field(default_factory=dict)


def coefficient_error(accepted: dict, effect: dict) -> float | None:
    """Relative error |fitted - true| / |true| of the accepted effect against gt/effects.json.

    A concealed value of zero (frictionless bodies) has no relative error; there the error is
    relative to the concealed change instead, |fitted - true| / |true - assumed|, with the
    assumed value recovered from the fitted value and its change (``friction_change``).
    """
    true = effect["params"]
    value = accepted["value"]
    if effect["kind"] == "ground_friction":
        fitted, truth = [value["ground_friction"]], [true["coefficient"]]
    else:
        name = next(iter(true))
        if name not in value:
            return None
        fitted = value[name] if isinstance(value[name], list) else [value[name]]
        truth = true[name] if isinstance(true[name], list) else [true[name]]
    diff = math.sqrt(sum((a - b) ** 2 for a, b in zip(fitted, truth)))
    norm = math.sqrt(sum(b * b for b in truth))
    if norm == 0.0 and "friction_change" in value and len(fitted) == 1:
        assumed = fitted[0] - value["friction_change"]
        norm = abs(truth[0] - assumed)
    if norm == 0.0:
        return None  # neither a true value nor a concealed change to compare with
    return diff / norm


def candidate_kind(name: str) -> str:
    """The effect kind a candidate name stands for (``plasticity@2`` -> ``plasticity``)."""
    return name.split("@", 1)[0]


def score_entry(
    entry: Entry, diagnosis: dict, effects: list[dict], law: dict | None = None
) -> Score:
    """How the diagnosis did on ``entry`` against the concealed ``effects``; ``law``: the
    discovered law's score against an out-of-library field (``law_score``), kept in extra."""
    accepted = diagnosis.get("accepted")
    ranked = diagnosis["evidence"][0]["name"] if diagnosis["evidence"] else None
    errors = diagnosis["errors"]
    reduction = None
    if accepted is not None:
        before = errors["identified"]["future_cd_mm2"]
        after = errors[accepted["name"]]["future_cd_mm2"]
        if before:
            reduction = 1.0 - after / before
    if not entry.conceal:
        correct = accepted is None
    elif entry.outside:
        # both verdicts say the residual is real and no candidate in the library explains it;
        # so does an accepted discovered law (the ``expression`` candidate), which names none
        correct = diagnosis["verdict"] in ("unexplained", "discrepancy") or (
            accepted is not None and candidate_kind(accepted["name"]) == EXPRESSION
        )
    else:
        correct = accepted is not None and candidate_kind(accepted["name"]) == entry.kind
    coef = None
    if accepted is not None and effects and candidate_kind(accepted["name"]) == effects[0]["kind"]:
        coef = coefficient_error(accepted, effects[0])
    extra = dict(law or {})
    if entry.outside:
        extra.update(law_future_reduction(errors))
    return Score(
        entry.name,
        entry.conceal or "-",
        diagnosis["verdict"],
        accepted["name"] if accepted else None,
        ranked,
        correct,
        float(diagnosis["where"]["signal_to_noise"]),
        coef,
        reduction,
        extra,
    )


def law_future_reduction(errors: dict) -> dict:
    """{"law_future_reduction": 1 - the discovered law's future Chamfer over the identified
    model's}, where the diagnosis tested the law as a model (its ``expression`` row), accepted
    or not: how much of the future an out-of-library field's law predicts. Empty otherwise."""
    before = errors.get("identified", {}).get("future_cd_mm2")
    after = errors.get(EXPRESSION, {}).get("future_cd_mm2")
    if not before or after is None:
        return {}
    return {"law_future_reduction": 1.0 - after / before}


def entry_overrides(entry: Entry, run_dir: Path) -> list[str]:
    """The recipe overrides that make the suite's recipe run ``entry`` into ``run_dir``."""
    overrides = [
        f"scene.path={run_dir / 'scene'}",
        f"output.dir={run_dir}",
        f"scene.source.materials={entry.materials}",
        f"scene.source.seed={entry.seed}",
    ]
    if entry.conceal:
        overrides.append(f"scene.source.conceal='{entry.conceal}'")
    if entry.exclude:
        overrides.append(f"diagnose.exclude=[{entry.exclude}]")
    return overrides + list(entry.overrides)


def run_entry(
    entry: Entry,
    out: Path,
    recipe_path: Path,
    budget: str,
    prepare_only: bool = False,
    scenes_only: bool = False,
) -> Score | None:
    """Generate, run, diagnose and score one entry into ``out/entry.name``.

    The score is written atomically to ``score.json`` last, so a suite stopped part-way resumes
    from the entries without one (the pipeline itself resumes its finished stages).
    ``prepare_only``: stop after the pipeline (None is returned); ``scenes_only``: generate
    the scene and nothing else (None), see ``run_suite``. Also the
    body of a Ray task (``run_suite`` with ``jobs`` > 1 or a cluster), whose output goes to
    the entry's ``suite.log``.
    """
    run_dir = out / entry.name
    done = run_dir / "score.json"
    if done.exists():
        return load_score(done)
    log.info("entry %s: %s on %s", entry.name, entry.conceal or "control", entry.materials)
    recipe = load_recipe(recipe_path, entry_overrides(entry, run_dir))
    if scenes_only:  # an existing scene is kept: generate_scene never writes over one
        generate_scene(recipe.scene)
        read_scene(run_dir / "scene")  # a folder left there is a scene, or its problems named
        return None
    run_pipeline(recipe, run_dir=run_dir)
    if prepare_only:
        return None
    diagnosis = diagnose_run(run_dir, budget=budget)
    effects = read_scene(run_dir / "scene").gt_effects()  # scoring only, after diagnosis
    law = None
    if entry.outside:
        from mosiv_framework.diagnose.law_score import law_score

        law = law_score(scored_law(diagnosis), effects, run_dir / "scene")
    score = score_entry(entry, diagnosis, effects, law)
    tmp = done.with_suffix(".json.tmp")
    record = {FIELD: SCORE_FORMAT, **asdict(score)}
    tmp.write_text(json.dumps(record, indent=2, default=float) + "\n")
    os.replace(tmp, done)
    return score


def scored_law(diagnosis: dict) -> dict | None:
    """The law an out-of-library entry's diagnosis ends with: the discovered law refitted as a
    model where it was accepted (``expression``), else the discovered law where no library
    term was accepted (the discovery runs only then), else none."""
    accepted = diagnosis.get("accepted")
    if accepted is not None and candidate_kind(accepted["name"]) == EXPRESSION:
        return (diagnosis.get("formula") or {}).get("refitted") or diagnosis.get("discovered")
    return diagnosis.get("discovered") if accepted is None else None


def load_score(path: Path) -> Score:
    """An entry's score.json (with or without its ``format`` field, which is checked)."""
    data = json.loads(path.read_text())
    file_format(data, path, (SCORE_FORMAT,))
    data.pop(FIELD, None)
    return Score(**data)


def run_suite(
    out: str | Path,
    *,
    small: bool = True,
    recipe: str | Path | None = None,
    budget: str | None = None,
    entries: list[Entry] | None = None,
    only: list[str] | None = None,
    jobs: int | None = 1,
    ray_address: str | None = None,
    gpus_per_task: float | None = None,
    overrides: list[str] | None = None,
    prepare_only: bool = False,
    source: str = "synth",
    split: str | None = None,
    scenes_only: bool = False,
) -> dict:
    """Generate, run, diagnose and score every entry into ``out``; returns the summary
    (``summarise``, with ``missing``), also written to suite.json, suite.md and suite.png.

    ``source`` and ``split``: the synth suite (``small`` or full, no split) or the Genesis
    suite's ``dev`` or ``test`` split (``suite_splits``); a folder holds one of them only.

    ``only`` restricts the suite to the named entries. ``jobs`` > 1 (or None: as many as the
    cluster takes) or a ``ray_address`` runs every entry as a Ray task of its own
    (:func:`mosiv_framework.scale.run_tasks`: a local Ray unless ``ray_address`` is given,
    ``gpus_per_task`` GPUs each, an entry whose worker died run again from its finished
    stages and listed under ``retried``); ``jobs=1`` runs them here one after another.
    ``overrides`` (``key=value``) apply to every entry's recipe, e.g.
    ``diagnose.refit_velocity_lr=1e-4``. Entries already scored in ``out`` are not recomputed.

    ``prepare_only`` generates and runs the entries' pipelines (synthesis, identification,
    evaluation) without diagnosing them, and returns ``{"prepared": [names]}``. Why: those
    stages are about a third of an entry's time, and a suite prepared on one machine is
    diagnosed on another from its finished stages, wherever ``out`` lies there (a stage's key
    holds the scene's content, not its path).

    ``scenes_only`` generates the entries' scenes and nothing else, and returns
    ``{"generated": [names]}``. Why: a scene source may need an engine that the GPU machine
    lacks (the Genesis suite needs genesis-world); the scenes are made where it is installed,
    and the folder, copied anywhere, is then run and diagnosed there.
    """
    if prepare_only and scenes_only:
        raise ConfigError("prepare_only and scenes_only: give one of them")
    out = Path(out)
    if entries is None:
        entries = suite_selection(small, source, split)
    check_suite_folder(out, source, split)
    out.mkdir(parents=True, exist_ok=True)
    (out / SUITE_MARKER).write_text(json.dumps({"source": source, "split": split}) + "\n")
    recipe_path = Path(recipe) if recipe is not None else default_recipe(small, source)
    budget = budget or ("small" if small else "full")
    entries = _chosen_entries(
        list(entries),
        only=only,
        overrides=overrides,
        recipe_path=recipe_path,
        out=out,
    )
    tasks = [
        Task(
            e.name,
            run_entry,
            (e, out, recipe_path, budget, prepare_only, scenes_only),
            out / e.name / "suite.log",
        )
        for e in entries
    ]
    outcomes = run_tasks(tasks, ray_address=ray_address, jobs=jobs, gpus_per_task=gpus_per_task)
    results = {name: o.result for name, o in outcomes.items() if o.ok}
    retried = [name for name, o in outcomes.items() if o.retried]
    if prepare_only or scenes_only:  # None: prepared or generated, not diagnosed
        done = sorted(name for name, score in results.items() if score is None)
        key = "prepared" if prepare_only else "generated"
        return {key: done, **({"retried": retried} if retried else {})}
    scores = {n: s for n, s in results.items() if s is not None}
    return _write_summary(out, entries, scores, retried, {"source": source, "split": split})


def suite_selection(small: bool, source: str = "synth", split: str | None = None) -> list[Entry]:
    """The entries of the synth suite (small or full) or of a split of another source's suite
    (``suite_splits``); an out-of-library kind that a registered physics term is named after is
    refused, since the diagnosis would then have it in its library."""
    from mosiv_framework.diagnose.suite_splits import split_entries

    entries = split_entries(source, split, small=small)
    if entries is None:
        return suite_entries(small)
    from mosiv_framework.registry import get_registry

    clash = library_conflicts(get_registry().names("physics_term"))
    if clash:
        raise ConfigError(
            f"physics term(s) {clash} are registered under out-of-library effect names: the "
            "suite's out-of-library entries would be in the library; rename the term(s)"
        )
    return entries


def default_recipe(small: bool, source: str = "synth") -> Path:
    """The recipe a suite runs with unless another is given."""
    from mosiv_framework.diagnose.suite_splits import SPLIT_RECIPES

    return SPLIT_RECIPES.get(source, DEFAULT_RECIPES[small])


#: the file in a suite folder that names the suite it holds (written when a run starts)
SUITE_MARKER = "suite_source.json"


def check_suite_folder(out: Path, source: str, split: str | None) -> None:
    """Refuse a folder that holds another source's or split's suite (its ``SUITE_MARKER`` or
    suite.json says so; a suite.json without them is the synth suite's). Why: the splits share
    entry names, and an entry's finished scene and score would be reused across them."""
    for name in (SUITE_MARKER, "suite.json"):
        path = out / name
        if not path.is_file():
            continue
        data = json.loads(path.read_text())
        was = (data.get("source", "synth"), data.get("split"))
        if was != (source, split):
            raise ConfigError(
                f"{path} holds the suite of source {was[0]!r}, split {was[1]!r}, not "
                f"{source!r}, {split!r}: use another folder, or give --source/--split as it "
                "was run"
            )


def _chosen_entries(
    entries: list[Entry],
    *,
    only: list[str] | None,
    overrides: list[str] | None,
    recipe_path: Path,
    out: Path,
) -> list[Entry]:
    """``entries`` restricted to ``only`` (unknown names refused with the valid ones), each
    with ``overrides`` added to its own; the recipe with them is loaded once here, rather than
    failing every entry the same way."""
    if only:
        known = {e.name for e in entries}
        unknown = sorted(set(only) - known)
        if unknown:
            raise ConfigError(f"suite entries {unknown} do not exist; valid: {sorted(known)}")
        entries = [e for e in entries if e.name in only]
    if overrides:
        entries = [replace(e, overrides=(*e.overrides, *overrides)) for e in entries]
        if entries:
            load_recipe(recipe_path, entry_overrides(entries[0], out / entries[0].name))
    return entries


def _write_summary(
    out: Path, entries: list[Entry], scores: dict[str, Score], retried: list[str], which: dict
) -> dict:
    """The summary of the scored entries (in suite order; the others ``missing``; those
    whose worker died and that ran again ``retried``; ``which``: the source and split), written
    to suite.json, suite.md and, if any was scored, suite.png."""
    ordered = [scores[e.name] for e in entries if e.name in scores]
    summary = summarise(ordered)
    summary["missing"] = [e.name for e in entries if e.name not in scores]
    summary["retried"] = retried
    summary.update(which)
    record = {FIELD: SUITE_FORMAT, **summary}
    (out / "suite.json").write_text(json.dumps(record, indent=2, default=float) + "\n")
    (out / "suite.md").write_text(table(summary) + "\n")
    if ordered:
        from mosiv_framework.diagnose.suite_plot import plot_suite

        plot_suite(summary, out / "suite.png")
    return summary


def entry_group(name: str, concealed: str) -> str:
    """'control' (nothing concealed), 'outside' (an effect outside the library, which the
    suite's entry names say) or 'concealed'."""
    if concealed == "-":
        return "control"
    return "outside" if "outside" in name else "concealed"


def summarise(scores: list[Score]) -> dict:
    groups = {g: [] for g in ("concealed", "control", "outside")}
    for s in scores:
        groups[entry_group(s.name, s.concealed)].append(s)
    concealed, controls, outside = groups["concealed"], groups["control"], groups["outside"]
    strong = [s for s in concealed if s.signal_to_noise >= 3.0]
    coefs = [s.coefficient_error for s in concealed if s.coefficient_error is not None]
    reductions = [s.future_reduction for s in concealed if s.future_reduction is not None]
    # the discovered laws of out-of-library fields (``law_score``), where scored
    laws = [s.extra["law_error"] for s in outside if s.extra.get("law_error") is not None]
    forms = [s for s in outside if s.extra.get("form_correct") is not None]
    law_futures = [s for s in outside if s.extra.get("law_future_reduction") is not None]

    def rate(items, pred):
        return sum(1 for s in items if pred(s)) / len(items) if items else None

    return {
        "scores": [asdict(s) for s in scores],
        "correct_first_rate": rate(strong, lambda s: s.correct),
        "control_false_discovery_rate": rate(controls, lambda s: s.accepted is not None),
        "outside_reported_unexplained_rate": rate(outside, lambda s: s.correct),
        "median_coefficient_error": statistics.median(coefs) if coefs else None,
        "median_future_reduction": statistics.median(reductions) if reductions else None,
        "outside_median_law_error": statistics.median(laws) if laws else None,
        "outside_law_form_rate": rate(forms, lambda s: s.extra["form_correct"]),
        # issue 40's bar for a discovered law: the future Chamfer at least halved
        "outside_law_future_halved_rate": rate(
            law_futures, lambda s: s.extra["law_future_reduction"] >= 0.5
        ),
    }


def table(summary: dict) -> str:
    def f(x, pct=False):
        if x is None:
            return "-"
        return f"{100 * x:.0f} %" if pct else f"{x:.3g}"

    lines = [
        "| scene | concealed | SNR | verdict | accepted | correct | coef. error "
        "| future-error reduction |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for s in summary["scores"]:
        future = f(s["future_reduction"], True)
        law_future = s["extra"].get("law_future_reduction")
        if s["future_reduction"] is None and law_future is not None:
            future = f"discovered law: {f(law_future, True)}"  # tested, not accepted
        lines.append(
            f"| {s['name']} | {s['concealed']} | {f(s['signal_to_noise'])} | {s['verdict']} | "
            f"{s['accepted'] or '-'} | {'yes' if s['correct'] else 'no'} | "
            f"{f(s['coefficient_error'], True)} | {future} |"
        )
    lines += [
        "",
        f"correct term first (SNR >= 3): {f(summary['correct_first_rate'], True)}; "
        f"false discoveries on controls: {f(summary['control_false_discovery_rate'], True)}; "
        "out-of-library reported unexplained: "
        f"{f(summary['outside_reported_unexplained_rate'], True)}; "
        f"median coefficient error: {f(summary['median_coefficient_error'], True)}; "
        f"median future-error reduction: {f(summary['median_future_reduction'], True)}",
    ]
    if any(
        summary.get(k) is not None
        for k in (
            "outside_median_law_error",
            "outside_law_form_rate",
            "outside_law_future_halved_rate",
        )
    ):
        lines.append(
            "out-of-library fields: median discovered-law error "
            f"{f(summary.get('outside_median_law_error'), True)}; law of the right form "
            f"{f(summary.get('outside_law_form_rate'), True)}; law's future Chamfer at least "
            f"halved {f(summary.get('outside_law_future_halved_rate'), True)}"
        )
    if summary.get("missing"):
        lines.append(f"not scored (failed or not yet run): {', '.join(summary['missing'])}")
    if summary.get("retried"):
        lines.append(f"run again after their worker died: {', '.join(summary['retried'])}")
    return "\n".join(lines)
