"""The text report of ``benchmarks/warp_profile.py``: the rows, the per-kernel table with the
forward beside each adjoint, the rate against the target, memory, the gradient check and the
parameter-gradient ablation (``warp_profile.Profile`` in, text out)."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the profile's record type; no import at run time (warp_profile imports this)
    from warp_profile import Profile


def _mib(b: int) -> str:
    return f"{b / 2**20:,.0f} MiB"


def report(p: Profile, target: float) -> str:
    """The profile as text: rows sorted by time with launches and share, phase totals, rates."""
    head = (
        f"{p.mode}: N={p.particles} grid={p.grid} substeps={p.substeps} family={p.family} "
        f"order={p.order} device={p.device}; timing: {p.timing}"
        + (
            f"; taped kernels read the parameter {p.parameter_reads}; "
            f"scatter adjoint {p.scatter_adjoint}"
            if p.mode == "backward"
            else ""
        )
    )
    lines = [head]
    if p.timing != "cuda activity":
        lines.append(
            "  (CPU: Warp times CUDA activity only, so each row is a launch group's wall time; "
            "the adjoint is timed per recorded launch)"
        )
    lines.append(f"  {'phase':<26} {'activity':<42} {'launches':>8} {'ms':>10} {'share':>6}")
    for r in p.rows:
        share = 100 * r.ms / p.total_ms if p.total_ms else 0.0
        lines.append(f"  {r.phase:<26} {r.name:<42} {r.launches:>8} {r.ms:>10.2f} {share:>5.1f}%")
    lines.append(f"  total {p.total_ms:.2f} ms (wall of the timed phases {p.wall_ms:.2f} ms)")
    work = p.particles * p.substeps
    if p.mode == "forward":
        lines.append(f"  throughput without graph: {p.rate:.3g} particle-substeps/s")
        return "\n".join(lines)
    phases = ", ".join(
        f"{k} {v:.2f}" for k, v in sorted(p.phase_totals().items(), key=lambda kv: -kv[1])
    )
    lines.append(f"  per phase (ms): {phases}")
    lines.append(kernel_table(p))
    lines.append(
        f"  forward frame {p.forward_ms:.2f} ms + backward {p.total_ms:.2f} ms "
        f"(backward / forward {p.total_ms / p.forward_ms:.1f}x): {p.rate:.3g} particle-substeps/s "
        "forward + backward, from the sums"
    )
    how = "captured CUDA graphs" if p.timing == "cuda activity" else "launched from Python"
    lines.append(
        f"  real path ({how}): forward {p.graph_forward_ms:.2f} ms + adjoint "
        f"{p.graph_backward_ms:.2f} ms a frame: {p.graph_rate:.3g} particle-substeps/s"
    )
    budget = work / target * 1e3
    lines.append(
        f"  target {target:.3g} particle-substeps/s: forward + backward within {budget:.2f} ms a "
        f"frame; the sums take {(p.forward_ms + p.total_ms) / budget:.1f}x that"
    )
    lines.append("  memory: " + ", ".join(f"{k} {_mib(v)}" for k, v in p.memory.items()))
    g = p.gradient_check
    worst = max(v for k, v in g.items() if k.endswith("_max_rel_diff"))
    same = "bit-identical" if g["bit_identical"] else f"largest relative difference {worst:.2g}"
    if not g["bit_identical"] and p.timing == "cuda activity":
        same += " (CUDA float atomics add in schedule order; --deterministic fixes it)"
    lines.append(f"  gradients of the profiled schedule vs the real path: {same}")
    if p.ablation is not None:
        lines.append(ablation_report(p))
    return "\n".join(lines)


#: kernels the taped replay records in place of the one it ran (their adjoints are that one's):
#: the replay's scatter runs as p2g and is taped as p2g_looped (transfer_kernels.py)
TAPED_AS = {"p2g_looped": "p2g"}


def kernel_table(p: Profile) -> str:
    """Per kernel, ms in the forward frame, the re-simulation, the taped replay and the adjoint,
    and the adjoint over one forward pass of it (the forward frame's, else the replay's; "-": not
    timed per kernel, as on the CPU); a kernel taped in another's place (TAPED_AS) gives its
    adjoint to that one's row."""
    cols = {"forward": {}, "re-simulation": {}, "taped replay": {}, "adjoint": {}}
    for r in [*p.forward_rows, *p.rows]:
        for prefix in ("forward kernel ", "backward kernel "):
            if r.phase in cols and r.name.startswith(prefix):
                name = r.name.removeprefix(prefix)
                cols[r.phase][TAPED_AS.get(name, name)] = r.ms
    names = sorted({k for c in cols.values() for k in c}, key=lambda k: -cols["adjoint"].get(k, 0))
    lines = [
        f"  per kernel (ms): {'kernel':<24} {'forward':>9} {'re-sim':>9} {'replay':>9} "
        f"{'adjoint':>9} {'adj/fwd':>8}"
    ]

    def cell(phase: str, name: str) -> str:
        return f"{cols[phase][name]:>9.2f}" if name in cols[phase] else f"{'-':>9}"

    for name in names:
        # the split transfers run only in the taped replay (the forward runs the fused ones)
        fwd = cols["forward"].get(name) or cols["taped replay"].get(name)
        adj = cols["adjoint"].get(name)
        ratio = f"{adj / fwd:>8.1f}" if fwd and adj is not None else f"{'-':>8}"
        row = " ".join(cell(ph, name) for ph in cols)
        lines.append(f"  {'':<17}{name:<24} {row} {ratio}")
    return "\n".join(lines)


def ablation_report(p: Profile) -> str:
    """Adjoint rows with and without the parameter tables' gradients (suspect 1)."""
    without = {(r["phase"], r["name"]): r["ms"] for r in p.ablation["rows"]}
    lines = ["  without parameter gradients (Warp skips the parameter atomics):"]
    for r in p.rows:
        if r.phase == "adjoint":
            other = without.get((r.phase, r.name), 0.0)
            lines.append(f"    {r.name:<42} {r.ms:>10.2f} -> {other:>10.2f} ms")
    total = p.ablation["total_ms"]
    rate = p.particles * p.substeps / ((p.forward_ms + total) / 1e3)
    lines.append(
        f"    backward total {p.total_ms:.2f} -> {total:.2f} ms: {rate:.3g} particle-substeps/s "
        "forward + backward"
    )
    return "\n".join(lines)
