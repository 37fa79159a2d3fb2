"""`eval samplers`: the samplers side by side, measured in one run (issue #27 item 4).

Rows: DDPM 50 and 8 on the base, EMDM and consistency at 4, 2 and 1 steps on their generators.
Quality (on the exported body, the default backend): realism (ASR, ANCR, naturalness and jitter
ratios, alive ratio, PRIMAL 5.1.1) and `eval control`'s mean errors. Speed, for each backend: ms per
0.5-s segment for one avatar with guidance and processing, and the largest crowd kept in real
time (powers of two). The two backends compute the same network (parity <= 1e-4, tests/test_onnx),
so quality is read once per sampler.
"""
from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

from ..io.atomic import write_file
from ..model.checkpoint import Motor
from ..runtime.crowd import RuntimeConfig
from .control import _time_segments, control
from .realism import realism

ROWS = (("ddpm", 50), ("ddpm", 8), ("emdm", 4), ("emdm", 2), ("emdm", 1),
        ("consistency", 4), ("consistency", 2), ("consistency", 1))


def largest_crowd(motor: Motor, cfg: RuntimeConfig, limit: int = 1024, seed: int = 0) -> int:
    """The largest power of two of avatars (with goals) whose segment takes < 0.5 s to make."""
    best, n = 0, 1
    while n <= limit:
        if _time_segments(motor, cfg, n, 2, True, seed)["total"] >= 0.5:
            break
        best, n = n, n * 2
    return best


def compare(models: dict[str, Motor], caches, backends=("onnxruntime", "torch"), n: int = 64, seconds: float = 8.0,
            control_n: int = 45, seed: int = 0, segments: int = 10, crowd_limit: int = 1024, progress=print) -> list[dict]:
    """models: {"ddpm": base, "emdm": generator, "consistency": student}; a missing kind skips its rows."""
    rows = []
    for kind, steps in ROWS:
        motor = models.get(kind)
        if motor is None:
            continue
        cfg = RuntimeConfig(steps=steps, backend=backends[0])
        name = f"{'DDPM' if kind == 'ddpm' else kind} {steps}"
        progress(f"{name}: realism")
        q = realism(motor, caches, n, seconds, seed, cfg, stability_seconds=0.0, progress=lambda *_: None)
        progress(f"{name}: control")
        c_rows, _, _ = control(motor, caches, control_n, 3.0, seed, cfg)
        guided = [r for r in c_rows if not math.isnan(r["vel_err"])]
        row = {"sampler": name, "kind": kind, "steps": steps, "model": motor.name,
               **{k: q[k] for k in ("ASR", "ANCR", "naturalness_ratio", "jitter_ratio", "alive", "alive_real")},
               "vel_err": sum(r["vel_err"] for r in guided) / len(guided),
               "dir_err": sum(r["dir_err"] for r in guided) / len(guided),
               "ASR_over_unguided": sum(r["ASR"] for r in guided) / len(guided) - c_rows[0]["ASR"]}
        for backend in backends:
            b = dataclasses.replace(cfg, backend=backend)
            progress(f"{name}: speed ({backend})")
            row[f"ms_{backend}"] = 1e3 * _time_segments(motor, b, 1, segments, True, seed)["total"]
            row[f"crowd_{backend}"] = largest_crowd(motor, b, crowd_limit, seed)
        rows.append(row)
    return rows


def format_rows(rows: list[dict], backends=("onnxruntime", "torch")) -> str:
    head = (f"{'sampler':14s} {'ASR':>6s} {'ANCR':>6s} {'nat.':>5s} {'jit.':>5s} {'alive':>5s} "
            f"{'vel.err':>7s} {'dir.err':>7s} {'dASR':>6s}")
    for b in backends:
        short = "ort" if b == "onnxruntime" else b
        head += f" {'ms ' + short:>9s} {'crowd ' + short:>11s}"
    out = [head]
    for r in rows:
        line = (f"{r['sampler']:14s} {r['ASR']:6.3f} {r['ANCR']:6.3f} {r['naturalness_ratio']:5.2f} "
                f"{r['jitter_ratio']:5.2f} {r['alive']:5.2f} {r['vel_err']:7.3f} {r['dir_err']:7.3f} "
                f"{r['ASR_over_unguided']:+6.3f}")
        for b in backends:
            line += f" {r[f'ms_{b}']:9.1f} {r[f'crowd_{b}']:11d}"
        out.append(line)
    if rows:
        out.append(f"alive ratio of real motion: {rows[0]['alive_real']:.2f}; ms: one avatar with guidance and "
                   "processing per 0.5-s segment; crowd: largest power of two kept in real time")
    return "\n".join(out)


def plot(rows: list[dict], png: str | Path, backend: str = "onnxruntime") -> None:
    """Quality against ms per segment: ASR, naturalness ratio and control velocity error."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 4))
    colors = {"ddpm": "tab:gray", "emdm": "tab:red", "consistency": "tab:blue"}
    for ax, key, label in zip(axes, ("ASR", "naturalness_ratio", "vel_err"),
                              ("foot skating (ASR)", "pose naturalness ratio", "control velocity error (m/s)")):
        for kind in colors:
            pts = sorted((r[f"ms_{backend}"], r[key], r["steps"]) for r in rows if r["kind"] == kind)
            if not pts:
                continue
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", color=colors[kind], label=kind)
            for x, y, s in pts:
                ax.annotate(str(s), (x, y), textcoords="offset points", xytext=(4, 4), fontsize=8)
        ax.set_xscale("log")
        ticks = [v for v in (5, 10, 20, 50, 100, 200, 500) if min(r[f"ms_{backend}"] for r in rows) / 1.5 <= v
                 <= max(r[f"ms_{backend}"] for r in rows) * 1.5]
        ax.set_xticks(ticks, [str(v) for v in ticks])
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        if key == "naturalness_ratio":
            ax.axhline(1.5, color="k", lw=0.8, ls="--", label="goal")
        ax.set_xlabel(f"ms per 0.5-s segment, one avatar ({backend})")
        ax.set_title(label)
        ax.grid(alpha=0.3)
    axes[0].legend()
    fig.tight_layout()
    write_file(png, lambda tmp: fig.savefig(tmp, dpi=90, format="png"))
    plt.close(fig)


def save_json(rows: list[dict], path: str | Path) -> None:
    write_file(path, lambda tmp: Path(tmp).write_text(json.dumps(rows, indent=1)))
