"""``rayfronts bench encoder``: image-encoder throughput with random weights (JSON result).

NARADIO: a random-weight RADIO v2.5 backbone of the real size + NACLIP last block + the
SigLIP head applied to every patch (as ``output=language`` would), frames/s over
``--frames`` frames after ``--warmup``; plus the last block alone, plain vs NACLIP, timed
on the same tokens in the same run (``naclip_overhead_ratio`` = NACLIP / plain).
Label encoder: MiniLM class-name embeddings pooled over random label images.
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

HELP = "image-encoder throughput (NARADIO with random weights, or the label encoder)"

LABEL_CLASSES = ["sky", "ground", "road", "building", "tree", "car", "fence", "chimney", "water tower",
                 "radio tower", "street lamp", "bench"]


def _res(s: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in s.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"resolution must be HxW (e.g. 224x224), got {s!r}") from None
    if h < 1 or w < 1:
        raise argparse.ArgumentTypeError(f"resolution must be positive, got {s!r}")
    return h, w


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", default="radio_v2.5-b", choices=["radio_v2.5-b", "radio_v2.5-l", "label"],
                        help="encoder to benchmark (RADIO models use random weights of the real size)")
    parser.add_argument("--resolution", type=_res, default=(224, 224), help="input size HxW in pixels")
    parser.add_argument("--frames", type=int, default=5, help="timed frames")
    parser.add_argument("--warmup", type=int, default=1, help="untimed frames first")
    parser.add_argument("--device", default="cpu", help="torch device (cpu, cuda, cuda:1)")
    parser.add_argument("--dtype", default="float32", choices=["float32", "float16", "bfloat16"],
                        help="compute dtype for NARADIO (CPU: float32)")
    parser.add_argument("--gauss-std", type=float, default=7.0, help="NACLIP Gaussian sigma in patches")
    parser.add_argument("--label-stride", type=int, default=8, help="label encoder output stride")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0 = torch default)")


def _sync(dev: torch.device):
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def _timeit(fn, n: int, warmup: int, dev: torch.device) -> list[float]:
    for _ in range(max(0, warmup)):
        fn()
    _sync(dev)
    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        _sync(dev)
        out.append(time.perf_counter() - t0)
    return out


def _label_image(h: int, w: int, rng) -> np.ndarray:
    lab = np.zeros((h, w), np.int32)
    lab[h // 3:] = 1
    for _ in range(20):
        y, x = rng.integers(0, h), rng.integers(0, w)
        lab[y:y + rng.integers(4, max(5, h // 4)), x:x + rng.integers(4, max(5, w // 4))] = rng.integers(0, 12)
    return lab


def run(args: argparse.Namespace) -> dict:
    if args.frames < 1:
        raise ValueError("--frames must be >= 1")
    if args.threads:
        torch.set_num_threads(args.threads)
    dev = torch.device(args.device)
    h, w = args.resolution
    rng = np.random.default_rng(0)
    res: dict = {"target": "encoder", "model": args.model, "resolution": [h, w], "frames": args.frames,
                 "device": str(dev), "torch_threads": torch.get_num_threads(), "torch": torch.__version__}
    if args.model == "label":
        from edge.encoders import EncoderConfig, make_encoder
        enc = make_encoder(EncoderConfig(kind="label", label_stride=args.label_stride), LABEL_CLASSES, device=dev)
        labs = [_label_image(h, w, rng) for _ in range(4)]
        i = iter(range(10 ** 9))
        times = _timeit(lambda: enc.encode(None, labs[next(i) % 4]), args.frames, args.warmup, dev)
        res.update(weights="MiniLM-L6 (real)", feature_shape=list(enc.encode(None, labs[0]).shape))
    else:
        from edge.encoders import EncoderConfig
        from edge.encoders.naradio import NaradioEncoder
        from edge.encoders.radio import RadioConfig
        from edge.encoders.random_init import random_checkpoint

        t0 = time.perf_counter()
        ck = random_checkpoint(RadioConfig.preset(args.model))
        cfg = EncoderConfig(kind="naradio", model=args.model, gauss_std=args.gauss_std, device=str(dev),
                            dtype=args.dtype, output="language")
        enc = NaradioEncoder(cfg, ckpt=ck)
        del ck
        res["build_s"] = round(time.perf_counter() - t0, 3)
        rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        times = _timeit(lambda: enc.encode(rgb), args.frames, args.warmup, dev)
        feat = enc.encode(rgb)
        # last block alone, plain vs NACLIP, on the same input tokens
        m = enc.model
        with torch.inference_mode():
            x = m.input_conditioner(enc.preprocess(rgb))
            t = m.base_model.patch_generator(x)
            for blk in m.base_model.blocks[:-1]:
                t = blk(t)
            hw = (x.shape[-2] // m.patch_size, x.shape[-1] // m.patch_size)
            plain, naclip = m.base_model.blocks[-1], enc.last_block
            reps = max(3, args.frames)
            tp = _timeit(lambda: plain(t, grid_hw=hw), reps, 1, dev)
            tn = _timeit(lambda: naclip(t, grid_hw=hw), reps, 1, dev)
            tok = torch.randn(hw[0] * hw[1], m.cfg.embed_dim, device=dev, dtype=enc.dtype)
            th = _timeit(lambda: enc.head(tok), reps, 1, dev)
        res.update(weights="random (real architecture)", feature_shape=list(feat.shape),
                   params_backbone_M=round(sum(p.numel() for p in m.parameters()) / 1e6, 1),
                   params_head_M=round(sum(p.numel() for p in enc.head.parameters()) / 1e6, 2),
                   last_block_plain_ms=round(1e3 * statistics.median(tp), 2),
                   last_block_naclip_ms=round(1e3 * statistics.median(tn), 2),
                   naclip_overhead_ratio=round(statistics.median(tn) / statistics.median(tp), 3),
                   head_all_patches_ms=round(1e3 * statistics.median(th), 2))
    med = statistics.median(times)
    res.update(s_per_frame_median=round(med, 4), s_per_frame_min=round(min(times), 4),
               fps=round(1.0 / med, 3))
    return res
