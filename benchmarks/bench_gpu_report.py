"""The GPU benchmark's outputs: the markdown table (with device, commit, command and method) and the JSON of
every row, rewritten after each row so that a run cut short keeps what it measured (bench_gpu.py)."""

from __future__ import annotations

import json
import math
from pathlib import Path


def _fmt(v, spec=".2f"):
    if v is None:
        return ""
    if isinstance(v, float) and math.isinf(v):
        return "inf"
    return format(v, spec)


def write_outputs(out: Path, meta: dict, rows: list[dict]) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps({**meta, "rows": rows}, indent=1, default=str) + "\n")
    unit = "ms (CUDA events)" if meta["timer"] == "cuda_events" else "ms (perf_counter)"
    lines = [
        f"# GPU benchmark: 3DGEER against gsplat{' (DRY RUN: CPU, tiny sizes)' if meta['dry_run'] else ''}",
        "",
        f"- device: {meta['device']}; torch {meta['torch']}; gsplat {meta['gsplat']}",
        f"- commit: {meta['commit']}",
        f"- command: `{meta['command']}`",
        (f"- config: {meta['config_path']}; warm-up {meta['timing']['warmup']}, median of {meta['timing']['repeats']} "
        f"runs (per-contender overrides in the config), timer: {unit}, one process, same inputs for all contenders"),
        ("- forward: no-grad forward. train fwd / bwd / fwd+bwd: one training iteration (loss sum(rgb * w)) timed "
        "in parts. Gaussians/tile over active tiles (geer: PBF lists; gsplat: tile intersections). Peak MiB: "
        "max_memory_allocated above the inputs (forward / training). Error: against the float64 brute-force "
        "render on the same rays (err rays = rays compared: all valid rays or a seeded subsample)."),
        "",
    ]
    for s in meta["scenes"]:
        lines.append(f"- scene {s['name']}: {s['n']} Gaussians; {s['note']}")
    for c in meta["cameras"]:
        lines.append(f"- camera {c['name']}: {c['width']}x{c['height']}, {c['model']}, {c['valid_rays']} valid rays; "
                     f"brute-force reference {c.get('ref_s', {})} s")
    lines += [
        "",
        ("| scene | camera | contender | forward ms | train fwd ms | bwd ms | fwd+bwd ms | Gaussians/tile mean | std | "
        "pairs | active tiles | visible | peak MiB fwd / train | max abs err | PSNR vs exact dB | err rays | note |"),
        "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |",
    ]
    for r in rows:
        peak = ""
        if r.get("peak_forward_mib") is not None or r.get("peak_train_mib") is not None:
            peak = f"{_fmt(r.get('peak_forward_mib'), '.0f')} / {_fmt(r.get('peak_train_mib'), '.0f')}"
        tiles = f"{r['active_tiles']}/{r['tiles']}" if "tiles" in r else ""
        lines.append(
            f"| {r['scene']} | {r['camera']} | {r['contender']} | {_fmt(r.get('forward_ms'))} | "
            f"{_fmt(r.get('train_forward_ms'))} | {_fmt(r.get('backward_ms'))} | {_fmt(r.get('fwd_bwd_ms'))} | "
            f"{_fmt(r.get('gpt_mean'), '.1f')} | {_fmt(r.get('gpt_std'), '.1f')} | {r.get('pairs', '')} | {tiles} | "
            f"{r.get('visible', '')} | {peak} | {_fmt(r.get('err_max'), '.2e')} | {_fmt(r.get('err_psnr'), '.1f')} | "
            f"{r.get('err_rays', '')} | {r.get('note', '')} |"
        )
    staged = [r for r in rows if r.get("stages_ms")]
    if staged:
        lines += ["", "## Stage timings (torch.profiler, device ms per training iteration, top kernels)", ""]
        for r in staged:
            top = list(r["stages_ms"].items())[:8]
            lines.append(f"- {r['scene']} / {r['camera']} / {r['contender']}: "
                         + "; ".join(f"`{k[:60]}` {v:.3f}" for k, v in top))
    out.write_text("\n".join(lines) + "\n")
