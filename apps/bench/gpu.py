"""``rayfronts bench gpu``: the GPU path in one command, one JSON, the paper beside it.

On a CUDA machine (``--device cuda``, the default) this runs, each as its own
``rayfronts bench`` process (so each has its own ``meta`` block and nothing leaks between
them):

* the encoder: NARADIO ``radio_v2.5-b`` and ``radio_v2.5-l`` (random weights of the real
  size: no weights needed), at 224×224 and 640×480, in each of ``--dtypes`` (default
  float16 and bfloat16);
* the mapper: the throughput and online presets with the map on the device;
* the end-to-end chain on loopback (router + mapper + edge processes, ``bench e2e --only
  stream --model radio_v2.5-b``: random real-size weights written to a model directory) in
  the paper's configuration: 224×224, NARADIO-B, PCA-100, throughput preset (30 cm voxels,
  no ray tracing), encoder and map on the device, in the first of ``--dtypes``.

It prints one JSON: every run's headline figures (and where its full JSON is), the GPU's
name and memory, and ``paper``: the paper's Jetson AGX Orin figures (8.84 Hz end to end
at 224², 30 cm, RADIO-B, PCA-100, no ray tracing; encoder 17.5 Hz) with our ratios to them.

``--device cpu --quick`` is the smoke test (tiny sizes, one model, few frames; CI runs it):
it proves the script and every stage run, not any figure. A run that fails is recorded
with its return code and last error line; the others still run. ``deploy/gpu_check.sh``
calls this command.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HELP = "the GPU path: encoder (NARADIO b/l, 224² and 640×480, fp16/bf16), mapper presets, e2e; paper comparison"

PAPER = {"platform": "NVIDIA Jetson AGX Orin", "e2e_hz": 8.84, "encoder_hz": 17.5,
         "e2e_config": "224x224, 0.3 m voxels, RADIO-B, PCA-100, no ray tracing"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--device", default="cuda", help="torch device (default cuda; cpu for the smoke test)")
    parser.add_argument("--quick", action="store_true",
                        help="tiny sizes and few frames (smoke test; figures meaningless)")
    parser.add_argument("--dtypes", default="float16,bfloat16",
                        help="encoder compute dtypes (default float16,bfloat16)")
    parser.add_argument("--models", default="radio_v2.5-b,radio_v2.5-l", help="NARADIO models (default b and l)")
    parser.add_argument("--resolutions", default="224x224,480x640",
                        help="encoder input sizes HxW (default 224x224,480x640)")
    parser.add_argument("--skip", default="", help="comma-separated stages to skip: encoder, mapper, e2e")
    parser.add_argument("--workdir", type=Path, default=None, help="keep each run's JSON and logs here")
    parser.add_argument("--timeout", type=float, default=1800.0, help="seconds per run (default 1800)")


def _csv(s: str) -> list[str]:
    return [x.strip() for x in str(s).split(",") if x.strip()]


def _device_info(device: str) -> dict:
    import torch

    info = {"device": device, "torch": torch.__version__, "cuda_available": torch.cuda.is_available()}
    if device.startswith("cuda") and torch.cuda.is_available():
        dev = torch.device(device)
        p = torch.cuda.get_device_properties(dev)
        info.update(name=p.name, memory_gb=round(p.total_memory / 2**30, 1), capability=f"{p.major}.{p.minor}",
                    cuda=torch.version.cuda, bf16_supported=bool(torch.cuda.is_bf16_supported()))
    return info


def _run(name: str, argv: list[str], work: Path, timeout: float) -> dict:
    """One ``rayfronts bench`` process; returns its JSON (or the failure)."""
    out = work / f"{name}.json"
    log = work / f"{name}.log"
    cmd = [sys.executable, "-m", "apps.cli", "bench", *argv, "--json", str(out)]
    print(f"[bench gpu] {name}: rayfronts bench {' '.join(argv)}", file=sys.stderr, flush=True)
    t = time.perf_counter()
    try:
        with open(log, "w") as f:
            rc = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=f, timeout=timeout).returncode
    except subprocess.TimeoutExpired:
        rc = 124
    rec = {"command": ["rayfronts", "bench", *argv], "rc": rc, "wall_s": round(time.perf_counter() - t, 1),
           "json": str(out)}
    if rc == 0 and out.exists():
        rec["result"] = json.loads(out.read_text())
    else:
        lines = log.read_text(errors="replace").strip().splitlines() if log.exists() else []
        rec["error"] = lines[-1] if lines else ("timed out" if rc == 124 else "no output")
        print(f"[bench gpu] {name} failed (rc {rc}): {rec['error']}", file=sys.stderr, flush=True)
    return rec


def _err(r: dict) -> dict:
    return {"rc": r["rc"], **({"error": r["error"]} if "error" in r else {})}


def _enc_summary(r: dict) -> dict:
    d = r.get("result") or {}
    return {"fps": d.get("fps"), "s_per_frame_median": d.get("s_per_frame_median"),
            "naclip_overhead_ratio": d.get("naclip_overhead_ratio"), **_err(r)}


def _map_summary(r: dict) -> dict:
    d = r.get("result") or {}
    return {"frames_per_s": d.get("frames_per_s"), "cpu_ms_per_frame": d.get("cpu_ms_per_frame"),
            "peak_rss_mb": d.get("peak_rss_mb"), "device": d.get("device"), **_err(r)}


def _e2e_summary(r: dict) -> dict:
    d = r.get("result") or {}
    return {"e2e_fps": d.get("e2e_fps"), "encoder_fps": d.get("encoder_fps"), "e2e_vs_encoder": d.get("e2e_vs_encoder"),
            "latency_ms": d.get("latency_ms"), "bytes_per_frame": (d.get("bytes_per_frame") or {}).get("mean"),
            "frames_mapped": d.get("e2e_frames_mapped"), **_err(r)}


def run(args: argparse.Namespace) -> dict:
    import torch

    from common.config import ConfigError

    dev = str(args.device)
    if dev.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"--device {dev}: CUDA is not available here (use --device cpu --quick for the smoke test)")
    skip = set(_csv(args.skip))
    bad = skip - {"encoder", "mapper", "e2e"}
    if bad:
        raise ConfigError(f"--skip: unknown stage(s) {', '.join(sorted(bad))}; choose encoder, mapper, e2e")
    dtypes = _csv(args.dtypes)
    models = _csv(args.models)
    resolutions = _csv(args.resolutions)
    if args.quick:
        models, resolutions = models[:1], ["64x64"]
    work = Path(args.workdir) if args.workdir else Path(tempfile.mkdtemp(prefix="rayfronts-bench-gpu-"))
    work.mkdir(parents=True, exist_ok=True)
    res: dict = {"target": "gpu", "quick": bool(args.quick), "device_info": _device_info(dev), "workdir": str(work),
                 "paper": dict(PAPER), "main_section": None}
    enc_frames, enc_warm = ("1", "0") if args.quick else ("30", "5")
    if "encoder" not in skip:
        res["encoder"] = {}
        for model in models:
            for r in resolutions:
                for dt in dtypes:
                    key = f"{model}@{r}@{dt}"
                    rec = _run(f"encoder_{model}_{r}_{dt}",
                               ["encoder", "--model", model, "--resolution", r, "--dtype", dt,
                                "--device", dev, "--frames", enc_frames, "--warmup", enc_warm], work, args.timeout)
                    res["encoder"][key] = _enc_summary(rec)
    if "mapper" not in skip:
        res["mapper"] = {}
        for preset, n in (("throughput", "6" if args.quick else "300"), ("online", "3" if args.quick else "100")):
            rec = _run(f"mapper_{preset}", ["mapper", "--preset", preset, "--frames", n, "--device", dev], work,
                       args.timeout)
            res["mapper"][preset] = _map_summary(rec)
    if "e2e" not in skip:
        dt = dtypes[0] if dtypes else "float32"
        rec = _run("e2e", ["e2e", "--only", "stream", "--frames", "6" if args.quick else "200",
                           "--resolution", "64x64" if args.quick else "224x224", "--pca-dim", "100",
                           "--preset", "throughput", "--model", "radio_v2.5-b", "--workdir", str(work / "e2e"),
                           "--edge-set", f"encoder.device={dev}", "--edge-set", f"encoder.dtype={dt}",
                           "--mapper-set", f"device={dev}"], work, args.timeout)
        res["e2e"] = _e2e_summary(rec)
        res["e2e"]["dtype"] = dt
    cmp: dict = {}
    e2e = (res.get("e2e") or {}).get("e2e_fps")
    if e2e:
        cmp["e2e_fps"] = e2e
        cmp["e2e_vs_paper"] = round(e2e / PAPER["e2e_hz"], 3)
    for key, v in (res.get("encoder") or {}).items():
        if v.get("fps"):
            cmp[f"encoder_vs_paper@{key}"] = round(v["fps"] / PAPER["encoder_hz"], 3)
    res["paper_comparison"] = cmp
    runs = [v for part in ("encoder", "mapper") for v in (res.get(part) or {}).values()] + (
        [res["e2e"]] if "e2e" in res else [])
    res["failed_runs"] = sum(1 for v in runs if v.get("rc") != 0)
    return res
