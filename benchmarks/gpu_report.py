"""GPU.md from the figures benchmarks/gpu.py stored in GPU.json, each beside what it compares with."""

from __future__ import annotations

from pathlib import Path

NOT_RUN = "not measured"


def _f(x, fmt: str = ".1f") -> str:
    if x is None:
        return NOT_RUN
    if isinstance(x, float):
        return format(x, fmt)
    return str(x)


_PAIR_WORDS = {
    "cpu_vs_f64": "CPU vs float64",
    "cpu_vs_cuda": "CPU vs CUDA",
    "cuda_vs_f64": "CUDA vs float64",
    "cpu_vs_triton": "CPU vs CUDA (triton)",
    "triton_vs_f64": "CUDA (triton) vs float64",
}


def _agreement(by_set: dict | None, note: str = "") -> list[str]:
    """The CPU and CUDA engines' relevancy images per query set, and each against the float64 reference."""
    if not by_set:
        return ["Agreement per query set: not measured in this run (added after it).", ""]
    keys = list(dict.fromkeys(k for w in by_set.values() for k in w))
    L = [
        "Agreement per query set (target: every figure <= 1e-4): max |relevancy difference| between the "
        "engines, and of each against a float64 dot-then-render of the stored embeddings." + note,
        "",
        "| query set | " + " | ".join(_PAIR_WORDS.get(k, k) for k in keys) + " |",
        "|---|" + "---:|" * len(keys),
    ]
    for name, w in by_set.items():
        L.append(f"| {name} | " + " | ".join(_f(w.get(k), ".2e") for k in keys) + " |")
    return [*L, ""]


def _grpc(g: dict | None, label: str) -> list[str]:
    """Where a served image's time goes (part pose, _grpc_breakdown), one server."""
    if not g:
        return []
    return [
        f"| {label}: raw stub, unary Render | {_f(g.get('sequential_ms'), '.2f')} | "
        f"{_f(g.get('sequential_images_per_s'))} |",
        f"| {label}: raw stub, single-threaded unary-stream channel option | "
        f"{_f(g.get('single_threaded_sequential_ms'), '.2f')} | "
        f"{_f(g.get('single_threaded_sequential_images_per_s'))} |",
        f"| {label}: thin client `FmgsClient.render` (decode included) | "
        f"{_f(g.get('client_render_ms'), '.2f')} | "
        f"{_f(g.get('client_render_images_per_s'))} |",
        f"| {label}: thin client pose stream (`stream`, poses sent as fast as the generator yields) | | "
        f"{_f(g.get('client_stream_images_per_s'))} |",
        f"| {label}: {g.get('grpc_concurrent_clients')} clients, unary | | "
        f"{_f(g.get('grpc_concurrent_images_per_s'))} ({g.get('grpc_concurrent_errors')} errors) |",
        f"| {label}: of one call, the server's render (elapsed_ms) | "
        f"{_f(g.get('server_render_ms'), '.2f')} | |",
        f"| {label}: of one call, a bare gRPC server echoing the same {g.get('response_bytes', 0):,} bytes "
        f"(plain / single-threaded option) | {_f(g.get('echo_floor_ms'), '.2f')} / "
        f"{_f(g.get('single_threaded_echo_floor_ms'), '.2f')} | |",
        f"| {label}: of one call, serialise / parse / client decode | "
        f"{_f(g.get('server_serialize_ms'), '.3f')} / {_f(g.get('client_parse_ms'), '.3f')} / "
        f"{_f(g.get('client_decode_ms'), '.3f')} | |",
    ]


def _status(p: dict | None) -> str | None:
    """Why a part has no figures (None when it has them)."""
    if p is None:
        return "not run"
    if isinstance(p.get("skipped"), str):  # a part left out (the tests part counts skipped tests)
        return f"skipped: {p['skipped']}"
    if "error" in p:
        return f"failed: {p['error']}"
    return None


def _paper(q: dict) -> list[str]:
    """The 899-channel render, gsplat against triton, errors and the launch sweep."""
    tri = "480x270_triton_stored_one_call_ms" in q
    L = ["| size | features | gsplat ms | gsplat FPS |" + (" triton ms | triton FPS |" if tri else ""),
         "|---|---|---:|---:|" + ("---:|---:|" if tri else "")]  # fmt: skip
    for tag in ("480x270", "648x420"):
        for name, what in (
            ("stored_one_call", "stored per Gaussian, one 899-channel render"),
            ("stored_three_calls", "stored, three renders (512, 384, 3)"),
            ("field_decoded", "decoded from the field (hash grid + heads) every frame"),
            ("5ch", "5 channels (a relevancy render's width)"),
        ):
            if f"{tag}_{name}_ms" not in q:
                continue
            row = f"| {tag} | {what} | {_f(q[f'{tag}_{name}_ms'], '.2f')} | {_f(q[f'{tag}_{name}_fps'])} |"
            if tri:
                row += f" {_f(q[f'{tag}_triton_{name}_ms'], '.2f')} | {_f(q[f'{tag}_triton_{name}_fps'])} |"
            L.append(row)
    L.append("")
    if tri:
        L += [
            f"Error of the 899-channel image at 480x270 against the float64 reference (max |difference| / "
            f"max |truth|): gsplat {_f(q.get('480x270_cuda_relmax_vs_f64'), '.1e')}, triton "
            f"{_f(q.get('480x270_triton_relmax_vs_f64'), '.1e')} (target 1e-4). The float64 projection and "
            "binning that precede the triton kernel (torch) take "
            f"{_f(q.get('480x270_project_bin_ms'), '.2f')} ms of each triton frame.",
            "",
        ]
    sw = q.get("sweep") or {}
    if sw:
        L += [
            "Triton launches (fmgs/render/triton_blend.py SWEEP; 480x270, through `rasterize`):",
            "",
            "| pixels per program | Gaussians per step | channels per program | alpha | products | warps | "
            "loop | 899 ch ms | FPS | 5 ch ms | rel. error |",
            "|---:|---:|---:|---|---|---:|---|---:|---:|---:|---:|",
        ]
        for r in sw.values():
            t = r["tuning"]
            if t.get("pipelined"):  # a launch of earlier runs (removed: slower than the single pass)
                loop = f"pipelined for, {t['stages']} stages"
            elif t.get("weights_once", 0) and 899 / t["block_channels"] >= t["weights_once"]:
                loop = f"weights once, then {t['stages']}-stage for"
            else:
                loop = "single pass (while)"
            head = (
                f"| {t['block_pixels']} | {t['block_gaussians']} | {t['block_channels']} | "
                f"{'float64' if t['geom64'] else 'float32'} | {t['precision']} | {t['num_warps']} | {loop} |"
            )
            if "error" in r:
                L.append(head + f" failed: {r['error'][:80]} | | | |")
            else:
                L.append(
                    head + f" {_f(r['ms'], '.2f')} | {_f(r['fps'])} | {_f(r['5ch_ms'], '.2f')} | "
                    f"{_f(r['relmax_vs_f64'], '.1e')} |"
                )
        L.append("")
    return L


def write_report(results: dict, path: Path) -> None:
    P = results.get("parts", {})
    env = P.get("env", {})
    L = [
        "# GPU figures",
        "",
        "Written by `python -m benchmarks.gpu --out DIR` on the machine named below; every figure here was",
        "measured there (medians after warm-up, device synchronised around each timed call). Figures marked",
        f"'{NOT_RUN}' were not measured. Raw numbers: GPU.json beside this file. Parts kept from",
        "earlier runs (`--resume`) name their machine, commit and date in the Parts table at the end.",
        "",
        "| | |",
        "|---|---|",
        f"| GPU | {env.get('nvidia_smi') or env.get('gpu') or NOT_RUN} |",
        f"| capability, SMs, memory | {env.get('capability', '?')}, {env.get('multiprocessors', '?')}, "
        f"{env.get('gpu_memory_gib', '?')} GiB |",
        f"| host | {env.get('cpu', '?')}, {env.get('cores', '?')} cores, {env.get('ram_gb', '?')} GB |",
        f"| software | torch {env.get('torch', '?')} (CUDA {env.get('torch_cuda', '?')}), "
        f"{env.get('nvcc', '?')}, "
        f"gsplat {env.get('gsplat', '?')}, Triton {env.get('triton', '?')}, "
        f"Python {env.get('python', '?')} |",
        f"| commit, date | {results.get('commit', '?')}, {env.get('date', '?')} |",
        "",
    ]
    b = P.get("build")
    t = P.get("tests")
    L += ["## Build and CUDA tests", ""]
    b = b or {}
    built = f"{_f(b.get('seconds'))} s to build or load (arch {b.get('arch')}, cached: {b.get('was_cached')})"
    L.append(f"- gsplat extension: {_status(b) or built}")
    if _status(t):
        L.append(f"- CUDA tests (`pytest -m cuda`): {_status(t)}")
    else:
        L.append(
            f"- CUDA tests (`pytest -m cuda`): {t['collected']} ran: {t['passed']} passed, "
            f"{t['failed']} failed, "
            f"{t['errors']} errors, {t['skipped']} skipped, in {_f(t['seconds'])} s."
        )
        L += [f"  - {x}" for x in t.get("failures", [])]
    L.append("")

    p = P.get("pose")
    L += ["## Pose query: relevancy image 480x270, 1M Gaussians (target >= 300 images/s)", ""]
    if _status(p):
        L += [_status(p), ""]
    else:
        L += [
            "| path | ms per image | images/s |",
            "|---|---:|---:|",
            f"| engine, CUDA with gsplat, same text (stream) | {_f(p['engine_cuda_cached_ms'], '.2f')} | "
            f"{_f(p['engine_cuda_cached_images_per_s'])} |",
            "| engine, CUDA with gsplat, new text each image | "
            f"{_f(p['engine_cuda_new_text_ms'], '.2f')} | "
            f"{_f(p['engine_cuda_new_text_images_per_s'])} |",
            "| engine, CUDA with gsplat, relevancy + RGB + depth | "
            f"{_f(p['engine_cuda_rel_rgb_depth_ms'], '.2f')} | "
            f"{_f(1e3 / p['engine_cuda_rel_rgb_depth_ms'])} |",
            *(
                [
                    f"| engine, CUDA with the triton backend, same text | "
                    f"{_f(p['engine_triton_cached_ms'], '.2f')} | "
                    f"{_f(p['engine_triton_cached_images_per_s'])} |",
                    f"| engine, CUDA with the triton backend, new text each image | "
                    f"{_f(p['engine_triton_new_text_ms'], '.2f')} | "
                    f"{_f(p['engine_triton_new_text_images_per_s'])} |",
                    f"| engine, CUDA with the triton backend, relevancy + RGB + depth | "
                    f"{_f(p['engine_triton_rel_rgb_depth_ms'], '.2f')} | "
                    f"{_f(1e3 / p['engine_triton_rel_rgb_depth_ms'])} |",
                ]
                if "engine_triton_cached_ms" in p
                else []
            ),
            f"| engine, CPU of the same machine | {_f(p['engine_cpu_ms'], '.1f')} | "
            f"{_f(p['engine_cpu_images_per_s'])} |",
            f"| gRPC loopback (gsplat), one client, sequential | {_f(p['grpc_sequential_ms'], '.2f')} | "
            f"{_f(p['grpc_sequential_images_per_s'])} |",
            f"| gRPC loopback (gsplat), {p['grpc_concurrent_clients']} clients | | "
            f"{_f(p['grpc_concurrent_images_per_s'])} "
            f"({p['grpc_concurrent_errors']} errors) |",
            *_grpc(p.get("grpc"), "gRPC, gsplat"),
            *_grpc(p.get("grpc_triton"), "gRPC, triton backend"),
            "",
            "CUDA engine (gsplat) vs CPU engine, same scene and text: max |relevancy difference| "
            f"{_f(p['cuda_vs_cpu_relevancy_max_abs'], '.2e')}; peak GPU memory "
            f"{_f(p['cuda_peak_gib'], '.2f')} GiB.",
            "",
        ]
        L += _agreement(p.get("agreement"), p.get("agreement_note", ""))
    q = P.get("paper")
    L += [
        "## The paper's full render: CLIP 512 + DINO 384 + RGB, garden (138,766 Gaussians)",
        "",
        f"Paper: {(q or {}).get('paper_fps', 103.4)} FPS at 480x270 on an RTX A5000; target 2x = 206.8 FPS.",
        "",
    ]
    if _status(q):
        L += [_status(q), ""]
    else:
        L += _paper(q)
    a = P.get("agreement")
    L += ["## Correctness on the device: gsplat against the reference backend", ""]
    if _status(a):
        L += [_status(a), ""]
    else:
        L += [
            "Same float32 inputs; f64 = the cpu backend in float64 (held to the brute force at "
            "1e-10 by the tests).",
            "Forward: max |difference| / max |truth| over the image.",
            "",
            "| channels | gsplat vs reference f32 | gsplat vs f64 | reference f32 vs f64 | "
            "alpha, gsplat vs f64 |",
            "|---:|---:|---:|---:|---:|",
        ]
        for D in (3, 5, 896):
            L.append(
                f"| {D} | {_f(a[f'fwd_D{D}_gsplat_vs_ref32_relmax'], '.1e')} | "
                f"{_f(a[f'fwd_D{D}_gsplat_vs_f64_relmax'], '.1e')} "
                f"| {_f(a[f'fwd_D{D}_ref32_vs_f64_relmax'], '.1e')} | "
                f"{_f(a[f'fwd_D{D}_alpha_gsplat_vs_f64_max_abs'], '.1e')} |"
            )
        L += [
            "",
            "Gradients (random cotangent), relative L2 error against the float64 reference:",
            "",
            "| channels | input | gsplat | reference f32 |",
            "|---:|---|---:|---:|",
        ]
        for D in (3, 5, 896):
            for nm in ("means", "quats", "scales", "opacities", "features"):
                L.append(
                    f"| {D} | {nm} | {_f(a[f'grad_D{D}_{nm}_gsplat_vs_f64_rel_l2'], '.1e')} "
                    f"| {_f(a[f'grad_D{D}_{nm}_ref32_vs_f64_rel_l2'], '.1e')} |"
                )
        L += [
            "",
            "The three documented rule differences, quantified:",
            "",
            f"- alpha clamp (gsplat 0.999, ours `alpha_max` 0.99), every opacity 1: max rel. difference "
            f"{_f(a['rule_alpha_clamp_opacity1_relmax'], '.2e')}, "
            f"{_f(100 * a['rule_alpha_clamp_pixels_differing_1e-3'], '.1f')}% of pixels differ by "
            "> 1e-3; with our "
            "`alpha_max=0.999` the difference falls to "
            f"{_f(a['rule_alpha_clamp_with_alpha_max_0.999_relmax'], '.2e')}.",
            "- termination (gsplat stops at T <= 1e-4, ours at T < 1e-4), a 2,000-layer stack: "
            "max rel. difference "
            f"{_f(a['rule_termination_deep_stack_relmax'], '.2e')} ({a['rule_termination_bound']}).",
            f"- float32 fast-math geometry, needle Gaussians (axis ratio 1e4): gsplat vs f64 "
            f"{_f(a['rule_fastmath_needles_gsplat_vs_f64_relmax'], '.2e')}, reference f32 vs f64 "
            f"{_f(a['rule_fastmath_needles_ref32_vs_f64_relmax'], '.2e')}.",
            "",
            f"Query engine on CUDA vs CPU ({a['engine_gaussians']:,} Gaussians, exact state, "
            "CLIP-like queries): "
            f"top-100 identical for {_f(100 * a['engine_text_top100_identical'], '.0f')}% of "
            "queries, max |relevancy "
            f"difference| {_f(a['engine_text_relevancy_max_abs'], '.1e')}; pose relevancy images "
            "max |difference| "
            f"{_f(a['engine_pose_relevancy_max_abs'], '.1e')}.",
            "",
        ]
    g = P.get("gs_train")
    L += ["## 3DGS training: snowmiku_small, full resolution (target held-out PSNR >= 25 dB)", ""]
    if _status(g):
        L += [_status(g), ""]
    else:
        sched = (
            "the full 30K-step schedule"
            if g["full_schedule"]
            else f"a schedule compressed to {g['steps']} steps"
        )
        L += [
            f"{g['steps']:,} steps ({sched}) at {g['image_size']}, {g['views_train']} training and "
            f"{g['views_heldout']} held-out views: {_f(g['train_s'])} s "
            f"({_f(g['train_s'] / 60, '.1f')} min), "
            f"{g['gaussians']:,} Gaussians, peak GPU memory {_f(g['peak_gpu_gib'], '.2f')} GiB; "
            "held-out PSNR "
            f"**{_f(g['heldout_psnr_db'], '.2f')} dB**, SSIM {_f(g['heldout_ssim'], '.3f')}.",
            "",
        ]
    f = P.get("field_train")
    L += ["## Field training: 4.2K steps, 512 + 384-channel targets (target <= 10 min; paper 1.4 h)", ""]
    if _status(f):
        L += [_status(f), ""]
    else:
        L += [
            "Targets from random-weight CLIP ViT-B/16 and DINO ViT-S/8 (float16, same cost as "
            "trained weights) for "
            f"{f['images']} images: {_f(f['extract_s'])} s ({_f(f['extract_images_per_s'])} images/s); maps "
            f"{f['map_size']} ("
            + (
                f"feature scale {f['feature_scale']}"
                if f.get("feature_scale")
                else f"longer side {f.get('feature_side')} px, the build default"
            )
            + ").",
            f"Training {f['steps']:,} steps on {f['selected_gaussians']:,} of {f['gaussians']:,} Gaussians "
            f"({f.get('geometry', 'gs_train fit')}): loop "
            f"{_f(f['train_loop_s'])} s ({_f(f['ms_per_step'], '.1f')} ms/step) + "
            f"{_f(f['prepare_s'])} s selection "
            f"and blending weights = **{_f(f['train_total_s'] / 60, '.1f')} min**"
            + (
                f"; with the targets, **{_f((f['train_total_s'] + f['extract_s']) / 60, '.1f')} min** in all"
                if f.get("full_schedule")
                else ""
            )
            + f"; peak GPU memory {_f(f['peak_gpu_gib'], '.2f')} GiB."
            + (
                ""
                if f.get("full_schedule", True)
                else f" Only {f['steps']:,} of 4,200 steps fitted in the part's time: 4,200 steps at this "
                f"rate would take {_f(f['projected_full_s'] / 60, '.1f')} min (projected, not measured)."
            ),
            "",
        ]
    x = P.get("text10m")
    L += ["## Text query at 10M Gaussians: CUDA engine against the CPU engine", ""]
    if _status(x):
        L += [_status(x), ""]
    else:
        L += [
            f"{x['gaussians']:,} embedded Gaussians, D={x['dim']}, top-{x['top_k']}, CLIP-like "
            "queries (median best "
            f"cosine to the scene {_f(x['query_best_cosine_median'], '.2f')}).",
            "",
            "| engine | open s | ms per query | top-100 vs exact |",
            "|---|---:|---:|---|",
            f"| CUDA, exact float32 ({_f(x['cuda_state_gib'], '.1f')} GiB on the GPU) | "
            f"{_f(x['cuda_open_s'])} | "
            f"{_f(x['cuda_ms_median'], '.2f')} | exact; identical to the CPU exact engine for "
            f"{_f(100 * x['cuda_vs_cpu_exact_top100_identical'], '.0f')}% |",
            f"| CPU, compact (default) | {_f(x['cpu_compact_open_s'])} | "
            f"{_f(x['cpu_compact_ms_median'], '.1f')} | "
            f"mean overlap {_f(100 * x['cpu_compact_top100_overlap_with_exact_mean'], '.1f')}%, worst "
            f"{_f(100 * x['cpu_compact_top100_overlap_with_exact_min'], '.0f')}% |",
            f"| CPU, exact float32 | {_f(x['cpu_exact_open_s'])} | "
            f"{_f(x['cpu_exact_ms_median'], '.1f')} | exact |",
            "",
            f"CUDA is {_f(x['speedup_cuda_vs_cpu_compact'])}x the CPU compact engine and "
            f"{_f(x['speedup_cuda_vs_cpu_exact'])}x the CPU exact engine on this machine.",
            "",
        ]
    c = P.get("chunks")
    if not _status(c):
        L += [
            "## gsplat channels per pass (`fmgs/render/cuda_gsplat.py: CHANNEL_CHUNK`)",
            "",
            "Garden at 480x270; the error column is the 899-channel image against the reference backend.",
            "",
            "| channels per pass | 899 channels, ms | 5 channels, ms | rel. error |",
            "|---:|---:|---:|---:|",
        ]
        for k in (8, 16, 32, 64, 128, 256, 513):
            if f"chunk{k}_899ch_ms" in c:
                L.append(
                    f"| {k} | {_f(c[f'chunk{k}_899ch_ms'], '.2f')} | {_f(c[f'chunk{k}_5ch_ms'], '.2f')} "
                    f"| {_f(c[f'chunk{k}_relmax_vs_reference'], '.1e')} |"
                )
        L.append("")
    if results.get("notes"):
        L += ["## Notes", ""] + [f"- {n}" for n in results["notes"]] + [""]
    L += ["## Parts", "", "| part | status | seconds | run |", "|---|---|---:|---|"]
    for name, part in P.items():
        st = _status(part) or "ok"
        secs = _f((part.get("_part") or {}).get("seconds"))
        L.append(f"| {name} | {st[:160]} | {secs} | {part.get('_run', '')} |")
    L.append("")
    path.write_text("\n".join(L))
