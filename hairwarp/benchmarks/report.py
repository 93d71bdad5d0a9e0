"""Charts (matplotlib, Agg) and the markdown report of a benchmark run, from its results alone."""

from __future__ import annotations

import math
from pathlib import Path

from hairwarp.benchmarks.common import machine_words

REPORT_NAME = "benchmarks.md"
CHARTS = {
    "dynamics": "bench_dynamics.png",
    "accuracy": "bench_accuracy.png",
    "convergence": "bench_convergence.png",
    "stability": "bench_stability.png",
    "scaling": "bench_scaling.png",
    "budget": "bench_budget.png",
}
OURS = ("semi_implicit", "implicit_joints")
PEER_ORDER = ("pinocchio", "pinocchio_aba_floor", "pinocchio_parallel", "mujoco_euler", "mujoco_euler_c_only",
              "mujoco_rollout_euler_t0", "mujoco_rollout_euler_threads", "newton_featherstone_tile", "newton_vbd")


def _g(x, digits: int = 3) -> str:
    if x is None:
        return "–"
    if isinstance(x, float) and not math.isfinite(x):
        return "∞"
    return f"{x:.{digits}g}"


def _dt(x) -> str:
    if x is None:
        return "< 1e-5"
    if x >= 1e-3:
        return f"{x * 1e3:.3g} ms (1/{1 / x:.0f} s)"
    return f"{x * 1e6:.3g} µs"


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.rcParams.update({"figure.dpi": 110, "axes.grid": True, "grid.alpha": 0.3, "font.size": 9})
    return plt


# ---------------------------------------------------------------------------------------------
# charts


def chart_dynamics(d: dict, path: Path):
    plt = _pyplot()
    configs = d["configs"]
    names = [f"hairwarp {i}" for i in OURS] + [p for p in PEER_ORDER if any(p in c["peers"] for c in configs)]
    fig, ax = plt.subplots(figsize=(10, 4.6))
    width = 0.8 / len(names)
    colors = plt.cm.tab10.colors
    for n, name in enumerate(names):
        xs, ys, missing = [], [], []
        for c, cfg in enumerate(configs):
            if name.startswith("hairwarp "):
                v = cfg["hairwarp"]["cpu"].get(name.split(" ", 1)[1], {}).get("seg_steps_per_s")
                status = "ok" if v else "error"
            else:
                r = cfg["peers"].get(name, {})
                status = r.get("status", "not run")
                v = r.get("seg_steps_per_s") if status == "ok" else None
            x = c + (n - len(names) / 2 + 0.5) * width
            if v:
                xs.append(x)
                ys.append(v)
            elif name in cfg["peers"] or name.startswith("hairwarp"):
                missing.append((x, status))
        label = d.get("peer_labels", {}).get(name, name)
        ax.bar(xs, ys, width * 0.95, label=label, color=colors[n % 10])
        for x, status in missing:
            ax.text(x, 1.2e3, status, rotation=90, ha="center", va="bottom", fontsize=7, color=colors[n % 10])
    ax.set_yscale("log")
    ax.set_ylim(1e3, None)
    ax.set_xticks(range(len(configs)))
    ax.set_xticklabels([f"{c['G']} strands x {c['S']} segments" for c in configs])
    ax.set_ylabel("segment-steps per second (higher is better)")
    ax.set_title("Strand dynamics throughput on the canonical scene, dt = 1 ms (threads as the table says)")
    ax.legend(fontsize=7, ncol=2, loc="upper center", bbox_to_anchor=(0.5, -0.12))
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def chart_accuracy(a: dict, path: Path):
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.6))
    markers = "osD^v<>ph*"
    methods = a.get("methods", [])
    long_key = "max_1" if any(r.get("max_1") is not None for m in methods for r in m.get("runs", [])) else "max_0.5"
    for n, m in enumerate(methods):
        runs = [r for r in m.get("runs", []) if r.get("cpu_s_per_sim_s")]
        if not runs:
            continue
        ours = m["kind"] == "hairwarp"
        style = {"marker": markers[n % len(markers)], "lw": 2.0 if ours else 1.0, "ls": "-" if ours else "--",
                 "ms": 5}
        for ax, key in zip(axes, ("rms_0.5", long_key)):
            pts = [(r["cpu_s_per_sim_s"], r.get(key)) for r in runs]
            ok = [(x, y) for x, y in pts if y is not None and y > 0]
            if ok:
                line, = ax.plot(*zip(*ok), label=m["method"], **style)
                for n_run, r in enumerate(runs):
                    if not ours and 0 < n_run < len(runs) - 1:
                        continue
                    if r.get(key) is not None and r.get(key) > 0:
                        ax.annotate(f"{r['dt']:g}", (r["cpu_s_per_sim_s"], r[key]), fontsize=5.5,
                                    color=line.get_color(), xytext=(3, 2), textcoords="offset points")
            blown = [r["cpu_s_per_sim_s"] for r in runs if r.get("finite") is False]
            if blown:
                ax.scatter(blown, [1.0] * len(blown), marker="x", color="k")
    span = "1 s" if long_key == "max_1" else "0.5 s"
    titles = ("tip error, RMS over 0.5 s", f"tip error, max over {span} (x at 1 m: blew up)")
    for ax, title in zip(axes, titles):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("CPU seconds per simulated second, one strand (lower is cheaper)")
        ax.set_ylabel("tip error [m]")
        ax.set_title(title)
    axes[0].legend(fontsize=7)
    fig.suptitle("Reference strand (20 segments, released from 80 deg): accuracy against cost; labels are dt [s]")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def chart_convergence(conv: dict, path: Path):
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    ticks = []
    for label, v in conv["variants"].items():
        S = [r["segments"] for r in v["rows"]]
        err = [r["max_vertex_error_m"] for r in v["rows"]]
        ax.plot(S, err, "o-", label=f"{label} (order {_g(v['fitted_order'], 2)})")
        ticks = S
    if ticks:
        s0, e0 = ticks[0], max(r["max_vertex_error_m"] for v in conv["variants"].values() for r in v["rows"])
        for order, ls in ((1, ":"), (2, "-.")):
            ax.plot(ticks, [e0 * (s0 / x) ** order for x in ticks], ls, color="0.5", lw=0.8, label=f"∝ 1/S^{order}")
    for tol in (1e-2, 1e-3, 1e-4):
        ax.axhline(tol, color="0.6", lw=0.7, ls="--")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xticks(ticks, [str(x) for x in ticks])
    ax.minorticks_off()
    ax.set_xlabel("segments S (same 0.3 m strand)")
    ax.set_ylabel("largest vertex distance to the continuum shape [m]")
    ax.set_title(f"Static cantilever, EI = {conv['bend_stiffness']:g} N m², tip sag {conv['tip_deflection_m']:.3g} m")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def chart_stability(s: dict, path: Path):
    plt = _pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(14, 4.6))
    ax = axes[0]
    for label, rows in s["vs_stiffness"].items():
        ax.plot([r["bend_stiffness"] for r in rows], [r["max_stable_dt"] or 5e-6 for r in rows], "o-",
                label=f"hairwarp {label}")
    mj = s.get("mujoco", {})
    if mj.get("status") == "ok":
        for n, (integ, rows) in enumerate(mj["results"].items()):
            ax.plot([r["bend_stiffness"] for r in rows], [r["max_stable_dt"] or 5e-6 for r in rows],
                    "s--" if n == 0 else "x:", mfc="none", ms=9 if n == 0 else 6, color="k" if n == 0 else "0.45",
                    label=f"MuJoCo {integ} (ball-joint stiffness)")
    nt = s.get("newton", {})
    if nt.get("status") == "ok":
        for rows in nt["results"].values():
            ax.plot([r["bend_stiffness"] for r in rows], [r["max_stable_dt"] or 5e-6 for r in rows], "D-.",
                    mfc="none", color="tab:purple", label="Newton VBD rods (root: free pivot)")
    ax.set_xlabel("bend stiffness EI [N m²]")
    ax.set_title("20 segments, released from 60 deg")
    ax = axes[1]
    colors = plt.cm.tab10.colors
    for integ, rows in s["vs_segments"].items():
        for n, ei in enumerate(sorted({r["bend_stiffness"] for r in rows})):
            sel = [r for r in rows if r["bend_stiffness"] == ei]
            ax.plot([r["segments"] for r in sel], [r["max_stable_dt"] or 5e-6 for r in sel],
                    "o-" if integ == "implicit_joints" else "^--", color=colors[n], label=f"{integ}, EI = {ei:g}")
    seg_ticks = sorted({r["segments"] for rows in s["vs_segments"].values() for r in rows})
    ax.set_xscale("log")
    ax.set_xticks(seg_ticks, [str(x) for x in seg_ticks])
    ax.minorticks_off()
    ax.set_xlabel("segments S (same 0.3 m strand)")
    ax.set_title("against segment count")
    ax = axes[2]
    for integ, rows in s["vs_mass_ratio"]["rows"].items():
        ax.plot([r["mass_ratio"] for r in rows], [r["max_stable_dt"] or 5e-6 for r in rows],
                "o-" if integ == "implicit_joints" else "^--", label=integ)
    ax.set_xlabel("tip / root segment mass (tapered radius)")
    ax.set_title(f"against taper, EI = {s['vs_mass_ratio']['bend_stiffness']:g} N m²")
    for ax in axes:
        if ax is not axes[1]:
            ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_ylim(4e-6, 0.08)
        ax.axhline(1 / 24, color="0.5", lw=0.8, ls=":")
        ax.axhline(1 / 240, color="r", lw=0.8, ls=":")
        ax.axhline(1e-3, color="0.5", lw=0.8, ls="--")
        ax.text(ax.get_xlim()[0], 1 / 240, " 1/240 s", color="r", fontsize=7, va="bottom")
        ax.text(ax.get_xlim()[0], 1 / 24, " 1/24 s", color="0.4", fontsize=7, va="bottom")
        ax.set_ylabel("largest stable dt [s] (5e-6: none)")
        ax.legend(fontsize=6.5)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def chart_scaling(sc: dict, path: Path):
    plt = _pyplot()
    pts = sc["devices"]["cpu"]["points"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.4))
    for S in sorted({p["S"] for p in pts}):
        sel = sorted((p for p in pts if p["S"] == S), key=lambda p: p["G"])
        axes[0].plot([p["G"] for p in sel], [p.get("step_s_min", p["step_s"]) * 1e3 for p in sel], "o-",
                     label=f"S = {S}")
    for G in sorted({p["G"] for p in pts}):
        sel = sorted((p for p in pts if p["G"] == G), key=lambda p: p["S"])
        axes[1].plot([p["S"] for p in sel], [p.get("step_s_min", p["step_s"]) * 1e3 for p in sel], "o-",
                     label=f"G = {G}")
    ex = sc["devices"]["cpu"]["exponents"]
    axes[0].set_xlabel("strands G")
    axes[0].set_title(f"cost vs strands (exponent at S = max: {_g(ex['vs_strands_largest_S'])})")
    axes[1].set_xlabel("segments per strand S")
    axes[1].set_title(f"cost vs segments (exponent at G = max: {_g(ex['vs_segments_largest_G'])})")
    for ax in axes:
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_ylabel("ms per step, fastest block (implicit_joints, CPU)")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


# ---------------------------------------------------------------------------------------------
# markdown


def _machine(m: dict) -> list[str]:
    v = m.get("versions", {})
    return [
        f"- CPU: {m.get('cpu')} ({m.get('cores')} cores), {m.get('platform')}",
        f"- Python {m.get('python')}; warp {v.get('warp')}, numpy {v.get('numpy')}, pin {v.get('pin')}, "
        f"mujoco {v.get('mujoco')}, newton {v.get('newton')}, scipy {v.get('scipy')}, matplotlib {v.get('matplotlib')}",
        f"- Date {m.get('date')}; hairwarp {m.get('hairwarp')} (commit {m.get('git_commit')}); load average at start "
        f"{m.get('load_average_start')}, at end {m.get('load_average_end')}",
    ]


def _suite_machines(s: dict) -> list[str]:
    """Which CPU each suite ran on, where the suites of this report ran on more than one (their ratios are taken
    within one run, on one machine; their absolute times are not comparable across them)."""
    by_cpu: dict[str, list[str]] = {}
    for name, data in s.items():
        by_cpu.setdefault(str(data.get("machine", {}).get("cpu")), []).append(name)
    if len(by_cpu) < 2:
        return []
    return ["- The suites ran on more than one machine (the footer of each section says which): "
            + "; ".join(f"{cpu}: {', '.join(names)}" for cpu, names in by_cpu.items())
            + ". Ratios are taken within one run; times in ms compare only within a suite."]


def _peer_figure(r: dict) -> str:
    if r.get("status") == "ok":
        return f"{_g(r.get('step_ms'))} ms, {_g(r['seg_steps_per_s'])}"
    return f"{r.get('status', '–')}"


def md_dynamics(d: dict) -> list[str]:
    out = ["## 1. Dynamics throughput (`hairwarp bench dynamics`)", "",
           f"![throughput]({CHARTS['dynamics']})", "",
           "Canonical scene of the peers' study: 0.3 m strands of solid cylinders (r = 2 mm, ρ = 1300 kg/m³), roots "
           "on a 1 cm grid at z = 1 m, first joint turned 80° about +y, gravity, joint damping 1e-10 N m s/rad, "
           "no joint springs, dt = 1 ms. Every figure below was measured in this run, on this machine, one after "
           "the other: the peers in child processes (one per peer and size, with a timeout). Protocol: one "
           "first step, 3 warm-up steps, median of 3 timed blocks of 100 steps (blocks halved to fit a time box; "
           "`downsized`)."
           + (f" hairwarp's launches run on {d['hairwarp_threads']} threads (every core this process may use, "
              "`Solver(threads=0)`; a captured graph replays on one), as do the peers marked \"every core\"; the "
              "others run on one." if d.get("hairwarp_threads") else ""), "",
           "| method | " + " | ".join(f"{c['G']}×{c['S']}: ms/step, seg-steps/s" for c in d["configs"]) + " |",
           "|---|" + "---|" * len(d["configs"])]
    for integ in OURS:
        cells = []
        for c in d["configs"]:
            r = c["hairwarp"]["cpu"].get(integ)
            if not r or not r.get("seg_steps_per_s"):
                cells.append("–")
                continue
            loaded = any(r[m].get("gate", {}).get("under_load") for m in ("launch", "graph"))
            cells.append(f"**{_g(r['step_ms'])} ms, {_g(r['seg_steps_per_s'])}** ({r['best_mode']}; launches "
                         f"{_g(r['launch'].get('step_ms'))} ms, graph {_g(r['graph'].get('step_ms'))} ms)"
                         + (" †" if loaded else ""))
        out.append(f"| hairwarp `{integ}` | " + " | ".join(cells) + " |")
    labels = d.get("peer_labels", {})
    for peer in PEER_ORDER:
        if not any(peer in c["peers"] for c in d["configs"]):
            continue
        cells = []
        for c in d["configs"]:
            r = c["peers"].get(peer, {"status": "not run"})
            if peer == "pinocchio_aba_floor" and r.get("status") == "ok":
                cells.append(f"{_g(r['us_per_call'])} µs/call, {_g(r['seg_steps_per_s'])}")
            elif peer == "mujoco_euler_c_only" and r.get("status") == "ok":
                cells.append(f"{_g(r['us_per_strand_step'])} µs/strand-step, {_g(r['seg_steps_per_s'])}")
            else:
                cell = _peer_figure(r)
                if r.get("downsized"):
                    cell += " (downsized)"
                if r.get("gate", {}).get("under_load"):
                    cell += " †"
                if r.get("status") not in (None, "ok") and r.get("message"):
                    cell += f": {r['message'][:90]}"
                cells.append(cell)
        out.append(f"| {labels.get(peer, peer)} | " + " | ".join(cells) + " |")
    out += ["", "### Ratios hairwarp / peer and the goals", "",
            "Ratio of segment-steps per second, hairwarp over the peer. The load of this shared machine drifts "
            "during a run, so the peer's child process also times hairwarp (its faster mode) just before and "
            "just after the peer's timed blocks; the ratio uses the geometric mean of those two timings (in "
            "brackets). All timings of hairwarp at each size are summarised below the table.", "",
            "| size | peer | goal | peer seg-steps/s | `semi_implicit` | `implicit_joints` | meets (semi / implicit) |",
            "|---|---|---|---|---|---|---|"]
    for c in d["configs"]:
        by = {}
        for r in c["ratios"]:
            by.setdefault(r["peer"], {})[r["integrator"]] = r
        for peer in PEER_ORDER:
            if peer not in by:
                continue
            rs = by[peer]
            goal = next(iter(rs.values()))["goal"]
            meets = " / ".join("–" if goal is None else ("yes" if rs.get(i, {}).get("meets") else "**no**")
                               for i in OURS)
            ratio_cells = []
            for i in OURS:
                r = rs.get(i, {})
                ratio_cells.append(f"{r['ratio']:.2f}× ({_g(r['ours_seg_steps_per_s'])})" if r.get("ratio")
                                   else r.get("peer_status") or "–")
            peer_fig = _g(next(iter(rs.values())).get("peer_seg_steps_per_s"))
            out.append(f"| {c['G']}×{c['S']} | {labels.get(peer, peer)} | {'≥ ' + _g(goal) + '×' if goal else 'info'}"
                       f" | {peer_fig} | {ratio_cells[0]} | {ratio_cells[1]} | {meets} |")
    out.append("")
    for c in d["configs"]:
        over = c.get("hairwarp_over_run", {})
        if over:
            out.append(f"- {c['G']}×{c['S']}: " + "; ".join(
                f"`{i}` median {_g(v['median'])} of {len(v['samples'])} timings, range {_g(v['min'])}–{_g(v['max'])}"
                for i, v in over.items()))
    ov = d.get("overhead_1x20", {})
    out += ["", "### Where a step's time goes", ""]
    shares = []
    for c in d["configs"]:
        for integ in OURS:
            gr = c["hairwarp"]["cpu"].get(integ, {}).get("graph", {}).get("step_s_min")
            over = d.get("overhead_1x20", {}).get(integ, {}).get("overhead_us")
            if gr and over:
                shares.append(f"{c['G']}×{c['S']} `{integ}` {100 * over / (over + gr * 1e6):.0f} %")
    if shares:
        out += ["The launch overhead of one step (measured on one strand, below) as a share of a plain step "
                "(that overhead plus the graph's fastest block) at each size: " + ", ".join(shares) + ".", ""]
    if ov:
        out.append("One strand of 20 segments (the step is then all overhead; fastest blocks): "
                   + "; ".join(f"`{k}` {v['launch_us']:.1f} µs per step with launches, {v['graph_us']:.1f} µs "
                               f"replayed from a captured graph, so **{v['overhead_us']:.1f} µs of Python launch "
                               "overhead per step**" for k, v in ov.items()) + ".")
        out.append("")
    if d.get("profile"):
        out += ["Wall time of each Warp call in a plain step on one thread (where CPU launches run when they are "
                "made), the three ABA passes alone on one thread (`Solver.joint_accelerations`, one "
                "`aba_accelerations` launch: no integration, no kinematics) and the compute per segment from the "
                "graph replay (one thread too):", "",
                "| size | integrator | calls per step | per call: ms/step | ABA alone: ms "
                "| graph ns per segment-step |",
                "|---|---|---|---|---|---|"]
        for p in d["profile"]:
            calls = ", ".join(f"`{k}` {v['ms_per_step']:.3g}" for k, v in p["calls"].items())
            cfg = next((c for c in d["configs"] if c["G"] == p["G"] and c["S"] == p["S"]), None)
            g = cfg["hairwarp"]["cpu"][p["integrator"]].get("graph", {}) if cfg else {}
            ns = g.get("step_s", 0) / (p["G"] * p["S"]) * 1e9 if g.get("step_s") else None
            out.append(f"| {p['G']}×{p['S']} | `{p['integrator']}` | {p['calls_per_step']:.0f} | {calls} | "
                       f"{_g(p.get('aba_only_ms'))} | {_g(ns)} |")
    cuda = d.get("cuda", {})
    where = f"measured on {cuda['device']} (section 5)" if cuda.get("device") else f"absent — {cuda.get('reason')}"
    out += ["", f"CUDA: {where}."]
    return out


def md_accuracy(a: dict) -> list[str]:
    ref = a.get("reference", {})
    out = ["## 2. Accuracy against cost (`hairwarp bench accuracy`)", "",
           f"![accuracy]({CHARTS['accuracy']})", "",
           "The peers' reference strand: 20 segments of 15 mm (r = 2 mm, ρ = 1300), root fixed at the origin, "
           "released from 80° with no damping and no joint springs; the tip whips at up to 7 m/s. Reference: "
           f"{ref.get('source')} at dt = {_g(ref.get('dt'))} s over {_g(a.get('duration_s'))} s"
           f"{' (cached in ' + ref['cached'] + ')' if ref.get('cached') else ''}; errors are tip distances sampled "
           "every 1 ms. " + a.get("cost_definition", "") + ".", ""]
    if a.get("status") == "no reference":
        return out + [f"No reference: {ref.get('status')} {ref.get('message')}"]
    out += ["| method | dt [s] | tip error RMS ≤ 0.5 s [m] | max ≤ 0.5 s [m] | max ≤ 1 s [m] | CPU s per simulated s |",
            "|---|---|---|---|---|---|"]
    for m in a["methods"]:
        if m.get("status") not in (None, "ok"):
            out.append(f"| {m['method']} | – | {m['status']}: {str(m.get('message'))[:80]} | | | |")
            continue
        for r in m["runs"]:
            bold = m["kind"] == "hairwarp" and r["dt"] in (1e-3, 1e-4)
            b = "**" if bold else ""
            out.append(f"| {b}{m['method']}{b} | {r['dt']:g} | {_g(r['rms_0.5'])} | {b}{_g(r['max_0.5'])}{b} | "
                       f"{b}{_g(r.get('max_1')) if r.get('finite', True) else 'blew up'}{b} | "
                       f"{_g(r['cpu_s_per_sim_s'])} |")
    conv = a.get("convergence")
    if conv:
        out += ["", "### Error against the continuum as the segment count grows", "",
                f"![convergence]({CHARTS['convergence']})", "",
                f"A horizontal clamped strand of {conv['length_m']} m, EI = {conv['bend_stiffness']:g} N m², sags "
                f"under its own weight (tip {conv['tip_deflection_m']:.3g} m below the root). {conv['method']}. "
                "Distances at equal arc length:", "",
                "| S | " + " | ".join(f"{k}: max vertex error [m]" for k in conv["variants"]) + " |",
                "|---|" + "---|" * len(conv["variants"])]
        first = next(iter(conv["variants"].values()))
        for n, row in enumerate(first["rows"]):
            out.append(f"| {row['segments']} | " + " | ".join(_g(v["rows"][n]["max_vertex_error_m"])
                                                             for v in conv["variants"].values()) + " |")
        for k, v in conv["variants"].items():
            few = v["fewest_segments_for_max_vertex_error"]
            most = max(r["segments"] for r in v["rows"])
            few_txt = " / ".join(str(few.get(t)) if few.get(t) else f"> {most}" for t in ("0.01", "0.001", "0.0001"))
            out.append(f"\n{k}: order {_g(v['fitted_order'], 2)}; fewest segments for a max vertex error of "
                       f"1 cm / 1 mm / 0.1 mm: {few_txt}.")
    return out


def _peer_stability(s: dict) -> dict:
    """Peer columns of the stiffness map: label -> rows."""
    cols = {f"MuJoCo `{k}`": v for k, v in s.get("mujoco", {}).get("results", {}).items()}
    for rows in s.get("newton", {}).get("results", {}).values():
        cols["Newton VBD rods"] = rows
    return cols


def _newton_note(s: dict) -> str:
    nt = s.get("newton", {})
    rows = next(iter(nt.get("results", {}).values()), [])
    if not rows:
        return "not run"
    return (f"{len(rows)} stiffnesses, steps from 1/24 s down to {min(nt.get('grid_used', [1e-4])):g} s, "
            f"{nt.get('duration_s', s['test']['duration_s']):g} s runs (a step costs ~1 ms from Python)")


def md_stability(s: dict) -> list[str]:
    t = s["test"]
    out = ["## 3. Stability (`hairwarp bench stability`)", "", f"![stability]({CHARTS['stability']})", "",
           f"Test: a {t['length_m']} m strand whose rest shape hangs straight down is released straight with its "
           f"root joint at {t['release_deg']:g}°, for {t['duration_s']:g} s ({t['side_duration_s']:g} s for the "
           f"segment and taper sweeps). Stable means {t['criteria']}, checked every {t['sample_s'] * 1e3:g} ms "
           f"(E: kinetic + gravity + joint springs; E_rest: the hanging rest shape). Largest stable dt by bisection "
           f"on a {t['grid_points']}-point log grid from {t['dt_min']:g} s to 1/24 s. Twist stiffness = EI, joint "
           f"damping {t['joint_damping_N_m_s']:g} N m s/rad (the canonical scene's) unless marked *hair damping* "
           f"(StrandParams default {t['hair_damping_N_m2_s']:g} N m² s, i.e. {t['hair_joint_damping_N_m_s']:.3g} "
           "N m s/rad per joint at 20 segments). MuJoCo: the same chain with `stiffness` on its ball joints "
           "equal to hairwarp's joint stiffness (root joint included; spring reference qpos0, the hanging "
           "shape) and the same damping. Newton VBD rods (`add_rod`, 10 iterations): bend and twist stiffness "
           "EI / L between segments; Newton 1.8 applies ball-joint springs in SolverMuJoCo only, so the root is a "
           "free pivot, and SolverFeatherstone, which applies none, has no place on this map; "
           f"{_newton_note(s)}.", "",
           "| EI [N m²] | " + " | ".join(f"`{k}`" for k in s["vs_stiffness"])
           + "".join(f" | {k}" for k in _peer_stability(s)) + " |",
           "|---|" + "---|" * (len(s["vs_stiffness"]) + len(_peer_stability(s)))]
    mj = {k: {r["bend_stiffness"]: r for r in v} for k, v in _peer_stability(s).items()}
    eis = [r["bend_stiffness"] for r in next(iter(s["vs_stiffness"].values()))]
    for n, ei in enumerate(eis):
        cells = []
        for rows in s["vs_stiffness"].values():
            r = rows[n]
            cells.append(_dt(r["max_stable_dt"]) + ("+" if r["at_top"] else "")
                         + (f" ({r['fails_above_because']})" if r.get("fails_above_because") else ""))
        for k in mj:
            r = mj[k].get(ei)
            cells.append("not run" if r is None else _dt(r["max_stable_dt"]) + ("+" if r["at_top"] else "")
                         + (f" ({r['fails_above_because']})" if r.get("fails_above_because") else ""))
        out.append(f"| {ei:g} | " + " | ".join(cells) + " |")
    for peer in ("mujoco", "newton"):
        if s.get(peer, {}).get("status") not in (None, "ok"):
            out.append(f"\n{peer}: {s[peer].get('status')} — {s[peer].get('message')}")
    f = s["findings"]
    out += ["", "`+`: stable at the largest step tried (1/24 s); in brackets, why the next grid step fails.", "",
            f"- `implicit_joints` is stable at 1/240 s or larger where `semi_implicit` is not, for EI = "
            f"{', '.join(f'{x:g}' for x in f['implicit_stable_semi_not_at_frame_dt']) or 'none'} N m².",
            f"- `implicit_joints` fails at 1/240 s for EI = "
            f"{', '.join(f'{x:g}' for x in f['implicit_fails_at_frame_dt']) or 'none of those tried'}, and at 1/24 s "
            f"for EI = {', '.join(f'{x:g}' for x in f['implicit_fails_at_1_24']) or 'none of those tried'}."]
    out += ["", "Against the segment count (same 0.3 m strand):", "",
            "| S | EI [N m²] | " + " | ".join(f"`{k}`" for k in s["vs_segments"]) + " |",
            "|---|---|" + "---|" * len(s["vs_segments"])]
    first = next(iter(s["vs_segments"].values()))
    for n, row in enumerate(first):
        out.append(f"| {row['segments']} | {row['bend_stiffness']:g} | "
                   + " | ".join(_dt(v[n]["max_stable_dt"]) + ("+" if v[n]["at_top"] else "")
                                + (f" ({v[n]['fails_above_because']})" if v[n].get("fails_above_because") else "")
                                for v in s["vs_segments"].values()) + " |")
    mr = s["vs_mass_ratio"]
    out += ["", f"Against the tip-to-root mass ratio (radius tapered geometrically, EI = {mr['bend_stiffness']:g} "
                "N m² kept):", "",
            "| tip/root mass | " + " | ".join(f"`{k}`" for k in mr["rows"]) + " |",
            "|---|" + "---|" * len(mr["rows"])]
    first = next(iter(mr["rows"].values()))
    for n, row in enumerate(first):
        out.append(f"| {row['mass_ratio']:g} | "
                   + " | ".join(_dt(v[n]["max_stable_dt"]) + ("+" if v[n]["at_top"] else "")
                                + (f" ({v[n]['fails_above_because']})" if v[n].get("fails_above_because") else "")
                                for v in mr["rows"].values()) + " |")
    return out


def _working_set_note(sc: dict) -> list[str]:
    """Why the largest grid points may cost more per segment: the step's arrays against the last-level cache."""
    ws = sc.get("working_set")
    if not ws:
        return []
    ex = sc["devices"]["cpu"]["exponents"]["vs_segments"]
    small = [v for k, v in ex.items() if int(k) < ws["G"] and v is not None]
    cache = f"this machine's {ws['l3_bytes'] / 2**20:.0f} MiB last-level cache (shared by its cores)" \
        if ws.get("l3_bytes") else "the last-level cache"
    return ["", f"A step at {ws['G']} × {ws['S']} works on {ws['bytes'] / 2**20:.1f} MiB of arrays "
                f"({ws['bytes_per_segment']:.0f} bytes a segment: the model, the solver's workspace, two states), "
                f"near {cache}, which other programs use too. The work per segment is the same at every size; "
                f"where the largest points cost more per segment, it is the cache, and their exponent against S "
                f"moves between runs by more than the goal's margin"
                + (f"; below {ws['G']} strands the largest exponent against S is {_g(max(small))} in this run."
                   if small else ".")]


def md_scaling(sc: dict) -> list[str]:
    ex = sc["devices"]["cpu"]["exponents"]
    pts = sc["devices"]["cpu"]["points"]
    out = ["## 4. Scaling (`hairwarp bench scaling`)", "", f"![scaling]({CHARTS['scaling']})", "",
           f"`{sc['integrator']}` step on the canonical scene, CPU, {sc['note']}. The table gives the fastest "
           "block's ms per step (segment-steps per second).", "",
           "| G \\ S | " + " | ".join(str(S) for S in sorted({p["S"] for p in pts})) + " |",
           "|---|" + "---|" * len({p["S"] for p in pts})]
    for G in sorted({p["G"] for p in pts}):
        row = {p["S"]: p for p in pts if p["G"] == G}
        out.append(f"| {G} | " + " | ".join(
            f"{row[S].get('step_s_min', row[S]['step_s']) * 1e3:.3g} ms "
            f"({_g(G * S / row[S].get('step_s_min', row[S]['step_s']))}/s)"
            + (" †" if row[S].get("under_load") else "") for S in sorted(row)) + " |")
    out += ["", "Fitted exponents of the cost (least squares in log-log; goal ≤ 1.1): vs strands "
            + ", ".join(f"{_g(v)} at S = {k}" for k, v in ex["vs_strands"].items()) + "; vs segments "
            + ", ".join(f"{_g(v)} at G = {k}" for k, v in ex["vs_segments"].items())
            + f". Largest: **{_g(sc['max_exponent'])}** — {'meets' if sc['meets'] else '**does not meet**'} the goal."
            + (" Fitted to the median blocks instead: vs strands "
               + ", ".join(f"{_g(v)}" for v in sc["devices"]["cpu"]["exponents_median"]["vs_strands"].values())
               + "; vs segments "
               + ", ".join(f"{_g(v)}" for v in sc["devices"]["cpu"]["exponents_median"]["vs_segments"].values())
               + "." if "exponents_median" in sc["devices"]["cpu"] else ""),
            *_working_set_note(sc),
            "", "Other stages (hooks: a module exposes `bench_<stage>(..., device=...)` returning a dict; it is "
            "called when it exists):", "", "| stage | hook | status | figures |", "|---|---|---|---|"]
    for st in sc["stages"]:
        fig = _stage_figures(st.get("result")) if st["status"] == "ok" else st.get("message", "")
        status = st["status"] + (" (quick sizes)" if st.get("quick") else "")
        out.append(f"| {st['stage']} | `{st['hook']}` | {status} | {fig} |")
    return out


def _times(d: dict, prefix: str = "", depth: int = 0) -> list[str]:
    """``name value ms`` for the keys ending in ``_s`` of a dict and of the dicts inside it (two levels)."""
    out = []
    for k, v in d.items():
        if k in ("build_s", "setup_s", "wall_s", "time_in_motion_s", "waited_s"):
            continue
        if k.endswith("_s") and isinstance(v, (int, float)) and not isinstance(v, bool):
            out.append(f"{prefix}{k[:-2].replace('_', ' ')} {_g(v * 1e3)} ms")
        elif isinstance(v, dict) and depth < 2:
            out += _times(v, f"{prefix}{k.replace('_', ' ')} ", depth + 1)
    return out


def _stage_figures(result, limit: int = 10) -> str:
    """The times of a hook's result, in ms: top level, then each entry of ``results`` (or ``margins``)."""
    if not isinstance(result, dict):
        return "–"
    head = ""
    if "strands" in result:
        head = f"{result['strands']} guides × {result.get('segments')} segments; "
    elif "guides" in result:
        head = f"{result['guides']} guides × {result.get('segments')} segments; "
    parts = _times({k: v for k, v in result.items() if k not in ("results", "margins")})
    for r in result.get("results") or result.get("margins") or []:
        if not isinstance(r, dict):
            continue
        label = r.get("state") or (f"{r['count']} dense strands" if "count" in r else "") or \
            (f"margin {r['margin']:g} m" if "margin" in r else "")
        times = ", ".join(_times({k: v for k, v in r.items() if not isinstance(v, list)})[:4])
        parts.append(f"{label}: {times}" if label else times)
    if result.get("status") not in (None, "ok"):
        return f"{result.get('status')}: {result.get('message', '')}"
    return head + "; ".join(parts[:limit]) if parts else "–"


def md_other(name: str, data: dict, out: Path) -> list[str]:
    """A suite another module provides: its charts (PNG files it lists) and its times, generically."""
    lines = [f"## Suite `{name}` (`hairwarp bench {name}`)", ""]
    for sub, value in data.items():
        if not isinstance(value, dict) or sub in ("machine", "quiet_gate"):
            continue
        for f in value.get("files", []):
            if str(f).endswith(".png") and Path(f).parent.resolve() == Path(out).resolve():
                lines += [f"![{sub}]({Path(f).name})", ""]
        figures = _stage_figures(value)
        lines.append(f"- {sub}: {figures if figures != '–' else 'see benchmarks.json'}")
    sm = data.get("machine", {})
    lines += ["", f"*Suite `{name}`: {data.get('wall_s')} s on {sm.get('date')}{machine_words(sm)}"
                  + ("; quick sizes" if data.get("quick") else "") + ".*"]
    return lines


# Suites run by name whose modules render their own report section: name -> (module, function(data) -> lines).
EXTRA_SECTIONS = {"interactions": ("hairwarp.benchmarks.interactions", "md_interactions"),
                  "dense": ("hairwarp.benchmarks.dense", "md_dense"),
                  "wedge": ("hairwarp.benchmarks.wedge", "md_wedge"),
                  "robustness": ("hairwarp.benchmarks.robustness", "md_robustness"),
                  "threads": ("hairwarp.benchmarks.threads", "md_threads")}


def _extra_section(name: str):
    """The section renderer a suite's module provides, or None (then ``md_other`` lists its figures)."""
    import importlib

    module, function = EXTRA_SECTIONS.get(name, (None, None))
    return getattr(importlib.import_module(module), function, None) if module else None


def md_cuda(s: dict) -> list[str]:
    """The CUDA column: figures when a suite ran on a CUDA device, else why they are absent."""
    out = ["## 6. CUDA", ""]
    rows = []
    for name in ("dynamics", "scaling"):
        cuda = s.get(name, {}).get("cuda")
        if not cuda:
            continue
        if not cuda.get("device"):
            out.append(f"- `{name}`: CUDA figures absent — {cuda.get('reason')}.")
            continue
        dev = cuda["device"]
        if name == "dynamics":
            for c in s[name]["configs"]:
                for integ, r in c["hairwarp"].get(dev, {}).items():
                    rows.append(f"| dynamics {c['G']}×{c['S']} | `{integ}` | {_g(r['launch'].get('step_ms'))} / "
                                f"{_g(r['graph'].get('step_ms'))} | {_g(r.get('seg_steps_per_s'))} |")
        else:
            for p in s[name]["devices"].get(dev, {}).get("points", []):
                rows.append(f"| scaling {p['G']}×{p['S']} | `{s[name]['integrator']}` | "
                            f"{_g(p['launch_step_s'] * 1e3)} / {_g(p['graph_step_s'] * 1e3)} | "
                            f"{_g(p['seg_steps_per_s'])} |")
    if rows:
        out += ["", "| figure | integrator | ms/step (launches / graph) | seg-steps/s |", "|---|---|---|---|", *rows]
    return out


def summary_lines(results: dict, suites=None) -> list[str]:
    """A short plain-text summary of the figures of ``suites`` (all in ``results`` when None)."""
    s = results.get("suites", {})
    names = suites or list(s)
    lines = []
    if "dynamics" in names and "dynamics" in s:
        d = s["dynamics"]
        lines.append("dynamics (seg-steps/s, best of launches and graph):")
        for c in d["configs"]:
            ours = ", ".join(f"{i} {_g(c['hairwarp']['cpu'][i].get('seg_steps_per_s'))}" for i in OURS
                             if i in c["hairwarp"]["cpu"])
            lines.append(f"  {c['G']} x {c['S']}: {ours}")
            for r in c["ratios"]:
                if r["goal"] is not None:
                    lines.append(f"    {r['integrator']:>15} / {r['peer']:<26} {_g(r['ratio'])}x "
                                 f"(goal >= {r['goal']:g}x: {'meets' if r['meets'] else 'NOT MET'})")
    if "accuracy" in names and "accuracy" in s:
        for m in s["accuracy"].get("methods", []):
            if m["kind"] == "hairwarp":
                lines.append(f"accuracy {m['integrator']}: " + ", ".join(
                    f"dt {r['dt']:g}: max0.5 {_g(r['max_0.5'])} m" for r in m["runs"]))
    if "stability" in names and "stability" in s:
        for label, rows in s["stability"]["vs_stiffness"].items():
            lines.append(f"stability {label}: " + ", ".join(f"EI {r['bend_stiffness']:g}: {_g(r['max_stable_dt'])}"
                                                           for r in rows))
    if "scaling" in names and "scaling" in s:
        sc = s["scaling"]
        lines.append(f"scaling: largest fitted exponent {_g(sc['max_exponent'])} (goal <= 1.1: "
                     f"{'meets' if sc['meets'] else 'NOT MET'})")
    if "budget" in names and "budget" in s:
        from hairwarp.benchmarks.budget import summary_budget

        lines.append(summary_budget(s["budget"]).removeprefix("- "))
    if "interactions" in names and "interactions" in s:
        for g in s["interactions"].get("goal", {}).values():
            if g is not None:
                lines.append(f"interactions: {g['strands']} guides, all stages {_g(g['per_dynamics'])}x the dynamics "
                             f"step (goal <= {s['interactions']['goal_per_dynamics']:g}x: "
                             f"{'meets' if g['meets'] else 'NOT MET'})")
        rows = [r for r in s["interactions"].get("scenes", {}).get("rows", []) if r.get("status") == "ok"]
        if rows:
            lines.append("interactions by shipped scene: " + ", ".join(
                f"{r['scene']} {_g(r['per_dynamics'])}x" for r in rows) + " the dynamics step (goal <= "
                f"{s['interactions']['goal_per_dynamics']:g}x: {sum(r['meets'] for r in rows)} of {len(rows)} meet)")
    if "robustness" in names and "robustness" in s:
        from hairwarp.benchmarks.robustness import summary

        lines += summary(s["robustness"])
    return lines


def _summary_md(s: dict) -> list[str]:
    out = ["## Summary", ""]
    d = s.get("dynamics")
    if d:
        out += ["| goal | size | `semi_implicit` | `implicit_joints` |", "|---|---|---|---|"]
        for c in d["configs"]:
            by = {}
            for r in c["ratios"]:
                if r["goal"] is not None:
                    by.setdefault(r["peer"], {})[r["integrator"]] = r
            for peer, rs in by.items():
                goal = next(iter(rs.values()))["goal"]
                cells = []
                for i in OURS:
                    r = rs.get(i, {})
                    cells.append(f"{r['ratio']:.2f}× {'✓' if r.get('meets') else '✗'}" if r.get("ratio")
                                 else f"{r.get('peer_status')} ✗")
                out.append(f"| ≥ {goal:g}× {d['peer_labels'].get(peer, peer)} | {c['G']}×{c['S']} | "
                           + " | ".join(cells) + " |")
        out.append("")
    a = s.get("accuracy")
    if a and a.get("methods"):
        out += ["Tip error of our integrators on the reference strand (max over 0.5 s / max over 1 s):", "",
                "| integrator | dt = 1e-3 | dt = 1e-4 |", "|---|---|---|"]
        for m in a["methods"]:
            if m["kind"] != "hairwarp":
                continue
            cells = []
            for dt in (1e-3, 1e-4):
                r = next((r for r in m["runs"] if abs(r["dt"] - dt) < 1e-12), None)
                cells.append("–" if r is None else f"{_g(r['max_0.5'])} m / "
                             f"{_g(r.get('max_1')) if r.get('finite', True) else 'blew up'} m")
            out.append(f"| `{m['integrator']}` | " + " | ".join(cells) + " |")
        out.append("")
    conv = (a or {}).get("convergence")
    if conv:
        parts = []
        for label, v in conv["variants"].items():
            row = next((r for r in v["rows"] if r["segments"] == 20), v["rows"][-1])
            parts.append(f"{label}: {_g(row['max_vertex_error_m'])} m at S = {row['segments']}, order "
                         f"{_g(v['fitted_order'], 2)}")
        out.append(f"- Static shape against the continuum (EI = {conv['bend_stiffness']:g} N m² cantilever): "
                   + "; ".join(parts) + ".")
    st = s.get("stability")
    if st:
        f = st["findings"]
        why = f.get("implicit_failure_reasons", {})

        def eis(values):
            return ", ".join(f"{x:g}" + (f" ({why[f'{x:g}']})" if why.get(f"{x:g}") else "") for x in values)

        out.append(f"- Stability: `implicit_joints` holds 1/240 s where `semi_implicit` fails for EI = "
                   f"{', '.join(f'{x:g}' for x in f['implicit_stable_semi_not_at_frame_dt']) or 'none'} N m². "
                   "`implicit_joints` itself fails at 1/240 s for EI = "
                   f"{eis(f['implicit_fails_at_frame_dt']) or 'none'}, and at 1/24 s for EI = "
                   f"{eis(f['implicit_fails_at_1_24']) or 'none'} N m².")
    sc = s.get("scaling")
    if sc:
        out.append(f"- Scaling: largest fitted cost exponent {_g(sc['max_exponent'])} over G × S up to "
                   f"{sc['largest']['G']} × {sc['largest']['S']} (goal ≤ 1.1: {'met' if sc['meets'] else 'not met'}).")
    if s.get("budget"):
        from hairwarp.benchmarks.budget import summary_budget

        out.append(summary_budget(s["budget"]))
    inter = s.get("interactions")
    rows = [r for r in ((inter or {}).get("scenes") or {}).get("rows", []) if r.get("status") == "ok"]
    if rows:
        goal = inter["goal_per_dynamics"]
        out.append(f"- Interactions (links and hair contacts) against the dynamics step, each shipped scene at its "
                   f"density (goal ≤ {goal:g}×): " + ", ".join(
                       f"{r['scene']} {r['per_dynamics']:.2f}× {'✓' if r['meets'] else '✗'}" for r in rows)
                   + f"; {sum(bool(r['meets']) for r in rows)} of {len(rows)} met.")
    rob = s.get("robustness")
    if rob:
        from hairwarp.benchmarks.robustness import summary_md

        out.append(summary_md(rob))
    return out + [""]


def write_report(results: dict, out: Path) -> Path:
    """Write the charts of every suite present and ``benchmarks.md`` into ``out``."""
    out = Path(out)
    s = results.get("suites", {})
    if "dynamics" in s:
        chart_dynamics(s["dynamics"], out / CHARTS["dynamics"])
    if "accuracy" in s and s["accuracy"].get("methods"):
        chart_accuracy(s["accuracy"], out / CHARTS["accuracy"])
        if s["accuracy"].get("convergence"):
            chart_convergence(s["accuracy"]["convergence"], out / CHARTS["convergence"])
    if "stability" in s:
        chart_stability(s["stability"], out / CHARTS["stability"])
    if "scaling" in s:
        chart_scaling(s["scaling"], out / CHARTS["scaling"])
    from hairwarp.benchmarks.budget import chart_budget, md_budget

    if "budget" in s:
        chart_budget(s["budget"], out / CHARTS["budget"])
    m = results.get("machine", {})
    lines = ["# Benchmarks", "",
             "Generated by `hairwarp bench` (`python -m hairwarp.bench`); every figure is in `benchmarks.json` "
             "beside this file, with the machine it was measured on. Do not edit by hand: rerun.", ""]
    quick = [k for k, v in s.items() if v.get("quick")]
    if quick:
        lines += [f"**Quick (smoke) sizes for: {', '.join(quick)}** — not the reference figures.", ""]
    lines += _machine(m) + _suite_machines(s) + [""]
    lines += _summary_md(s)
    for name, fn in (("dynamics", md_dynamics), ("accuracy", md_accuracy), ("stability", md_stability),
                     ("scaling", md_scaling), ("budget", md_budget)):
        if name in s:
            sm = s[name].get("machine", {})
            qg = s[name].get("quiet_gate", {})
            gate = ""
            if qg.get("enabled") and qg.get("timings"):
                gate = (f" Before each of its {qg['timings']} timings it waited for other programs to leave the "
                        f"cores ({qg['waited_s']} s in all); {qg['timings_under_load']} still started with others "
                        f"using ≥ {qg['threshold_cores']} core (marked †).")
            lines += fn(s[name]) + ["", f"*Suite `{name}`: {s[name].get('wall_s')} s on {sm.get('date')}"
                                        f"{machine_words(sm)}, load "
                                        f"average {sm.get('load_average_start')} → {sm.get('load_average_end')}."
                                        f"{gate}*", ""]
    for name in s:
        if name in ("dynamics", "accuracy", "stability", "scaling", "budget"):
            continue
        section = _extra_section(name)
        body = section(s[name]) if section else md_other(name, s[name], out)
        if not any(line.startswith("*Suite `") for line in body):  # when and where it ran, as every suite says
            sm = s[name].get("machine", {})
            body += ["", f"*Suite `{name}`: {s[name].get('wall_s')} s on {sm.get('date')}{machine_words(sm)}.*"]
        lines += body + [""]
    lines += md_cuda(s) + [""]
    lines += ["## Reproduce", "", "```", "hairwarp bench                 # all suites, about 15 min on 2 cores; "
              "writes docs/", "hairwarp bench dynamics --out /tmp/b   # one suite", "hairwarp bench --quick"
              "         # smoke run (~1 min) into out/bench-quick/", "```", "",
              "The machine is shared and noisy (the peers' study saw 10–25 % between runs of one configuration); "
              "ratios are taken between figures of the same run. A Warp CPU launch runs on one thread; hairwarp "
              "splits its launches over the threads of `--threads` (every core by default), and the peers marked "
              "\"every core\" use theirs; Pinocchio, the MuJoCo loop and rollout with 1 thread run on one."]
    path = out / REPORT_NAME
    path.write_text("\n".join(lines) + "\n")
    return path
