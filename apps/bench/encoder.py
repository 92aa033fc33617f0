"""``rayfronts bench encoder``: the image encoder as the edge runs it (JSON result).

NARADIO: the model is built exactly as ``rayfronts edge`` builds it — :func:`encoders.make_encoder`
on an ``EncoderConfig`` (``--output``, ``--dtype``, ``--device``) reading a checkpoint from a
model directory (``--model-dir``; default: random weights of the real architecture written to
a temporary model directory as ``<model>.safetensors``, i.e. the file a user gets from
``rayfronts models convert``), the torch thread count the edge uses (``edge.config.resolve_threads``,
or ``--threads``), and one timed call per frame of what the edge calls per frame,
``encode_with_global(rgb, global_space="features")`` (one forward pass: dense map + image
vector). Reported beside it, timed in alternation in the same process (``apps.bench.meta.interleaved``):
the same weights built in memory without the file (``in_memory_vs_loaded``, the old bench's
path), and the last block alone, plain vs NACLIP (``naclip_overhead_ratio``), and the head on
every patch.

The "4x" once seen between an in-memory random model (1.6 s per 224² frame) and the same
architecture loaded from a file (0.40 s) is not a property of either path: timed in
alternation in one process both take the same time (ratio 1.00 ± noise), neither has
denormal weights or activations (none counted; ``torch.set_flush_denormal`` changes
nothing), parameters have the same dtype and strides. The two figures were taken at
different moments on a 2-core machine shared with other processes; the load, not the model,
made the difference — hence the alternation and the load average in every result.

Label encoder: MiniLM class-name embeddings pooled over random label images (``encode_with_global``).
"""
from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np
import torch

from apps.bench.meta import resolution_arg

if TYPE_CHECKING:
    from edge.config import EdgeConfig
    from encoders import ImageEncoder

HELP = "image-encoder throughput (NARADIO with random weights, or the label encoder)"

LABEL_CLASSES = ["sky", "ground", "road", "building", "tree", "car", "fence", "chimney", "water tower",
                 "radio tower", "street lamp", "bench"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", default="radio_v2.5-b", choices=["radio_v2.5-b", "radio_v2.5-l", "label"],
                        help="encoder to benchmark (RADIO models: random weights of the real size unless "
                             "--model-dir holds a checkpoint)")
    parser.add_argument("--model-dir", default="", help="model directory with the RADIO checkpoint (as the edge's "
                                                        "encoder.model_dir); default: random weights in a temp dir")
    parser.add_argument("--output", default="radio", choices=["radio", "language"],
                        help="NARADIO output space (encoder.output, default radio as the edge)")
    parser.add_argument("--resolution", type=resolution_arg, default=(224, 224), help="input size HxW in pixels")
    parser.add_argument("--frames", type=int, default=5, help="timed frames")
    parser.add_argument("--warmup", type=int, default=1, help="untimed frames first")
    parser.add_argument("--device", default="cpu", help="torch device (cpu, cuda, cuda:1)")
    parser.add_argument("--dtype", default="float32", choices=["float32", "float16", "bfloat16"],
                        help="compute dtype for NARADIO (CPU: float32)")
    parser.add_argument("--gauss-std", type=float, default=7.0, help="NACLIP Gaussian sigma in patches")
    parser.add_argument("--label-stride", type=int, default=8, help="label encoder output stride")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0 = what the edge uses)")
    parser.add_argument("--no-in-memory", action="store_true", help="skip the in-memory comparison")


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


def random_model_dir(model: str, root: Path, dtype: torch.dtype | None = None) -> Path:
    """Write random weights of ``model``'s real architecture as ``<root>/<model>.safetensors``
    (our flat layout, what ``rayfronts models convert`` writes); returns ``root``."""
    from encoders.radio import RadioConfig, save_flat
    from encoders.random_init import random_checkpoint

    path = Path(root) / f"{model}.safetensors"
    if not path.is_file():
        save_flat(random_checkpoint(RadioConfig.preset(model)), path, dtype=dtype)
    return Path(root)


def edge_encoder(cfg_items: list[str], class_names: Sequence[str] | None = None
                 ) -> tuple[ImageEncoder, EdgeConfig, int]:
    """``(encoder, edge config, torch threads)`` built exactly as ``rayfronts edge`` builds them
    from the config overrides ``cfg_items`` (thread count: ``edge.config.resolve_threads``)."""
    from common.config import load_config
    from edge.config import EdgeConfig, resolve_threads
    from encoders import make_encoder

    ecfg = load_config(EdgeConfig, None, list(cfg_items))
    n = resolve_threads(ecfg) or torch.get_num_threads()
    torch.set_num_threads(n)
    return make_encoder(ecfg.encoder, class_names=class_names), ecfg, n


def run(args: argparse.Namespace) -> dict:
    import tempfile

    from apps.bench.meta import interleaved, timed

    if args.frames < 1:
        raise ValueError("--frames must be >= 1")
    dev = torch.device(args.device)
    h, w = args.resolution
    rng = np.random.default_rng(0)
    res: dict = {"target": "encoder", "model": args.model, "resolution": [h, w], "frames": args.frames,
                 "device": str(dev), "torch": torch.__version__}
    if args.model == "label":
        enc, _, n = edge_encoder(["encoder.kind=label", f"encoder.label_stride={args.label_stride}",
                                  f"encoder.device={dev}"] + ([f"threads={args.threads}"] if args.threads else []),
                                 LABEL_CLASSES)
        from encoders.label import LabelEncoder
        assert isinstance(enc, LabelEncoder)
        labs = [_label_image(h, w, rng) for _ in range(4)]
        i = iter(range(10 ** 9))
        with timed("encode", frames=args.frames):
            times = _timeit(lambda: enc.encode_with_global(None, labs[next(i) % 4], global_space="features"),
                            args.frames, args.warmup, dev)
        res.update(weights="MiniLM-L6 (real)", feature_shape=list(enc.encode(None, labs[0]).shape), torch_threads=n)
    else:
        tmp = None
        t0 = time.perf_counter()
        if args.model_dir:
            mdir, weights = Path(args.model_dir), "from --model-dir"
        else:
            tmp = tempfile.TemporaryDirectory(prefix="rayfronts-bench-encoder-")
            mdir, weights = random_model_dir(args.model, Path(tmp.name)), "random (real architecture), from a file"
        res["write_model_s"] = round(time.perf_counter() - t0, 3)
        t0 = time.perf_counter()
        items = ["encoder.kind=naradio", f"encoder.model={args.model}", f"encoder.model_dir={mdir}",
                 f"encoder.output={args.output}", f"encoder.dtype={args.dtype}", f"encoder.device={dev}",
                 f"encoder.gauss_std={args.gauss_std}"] + ([f"threads={args.threads}"] if args.threads else [])
        enc, ecfg, n = edge_encoder(items)
        from encoders.naradio import NaradioEncoder
        assert isinstance(enc, NaradioEncoder)
        res["build_s"] = round(time.perf_counter() - t0, 3)
        res.update(torch_threads=n, checkpoint=enc.checkpoint_path, output=args.output)
        rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        with timed("encode", frames=args.frames):
            times = _timeit(lambda: enc.encode_with_global(rgb, global_space="features"), args.frames,
                            args.warmup, dev)
        feat, gl = enc.encode_with_global(rgb, global_space="features")
        if not args.no_in_memory:
            # the same weights built in memory (no file): timed in alternation with the loaded model
            from encoders.radio import read_checkpoint

            mem = NaradioEncoder(ecfg.encoder, device=dev, ckpt=read_checkpoint(enc.checkpoint_path))
            reps = max(3, args.frames)
            t = interleaved({"loaded": lambda: enc.encode_with_global(rgb, global_space="features"),
                             "in_memory": lambda: mem.encode_with_global(rgb, global_space="features")},
                            reps, 1, sync=lambda: _sync(dev))
            res["interleaved_s_per_frame"] = {k: round(statistics.median(v), 4) for k, v in t.items()}
            res["in_memory_vs_loaded"] = round(statistics.median(t["in_memory"]) / statistics.median(t["loaded"]), 3)
            del mem
        # last block alone, plain vs NACLIP, on the same input tokens (alternated)
        m = enc.model
        with torch.inference_mode():
            x = m.input_conditioner(enc.preprocess(rgb))
            tk = m.base_model.patch_generator(x)
            for blk in m.base_model.blocks[:-1]:
                tk = blk(tk)
            hw = (x.shape[-2] // m.patch_size, x.shape[-1] // m.patch_size)
            plain, naclip = m.base_model.blocks[-1], enc.last_block
            reps = max(3, args.frames)
            fns = {"plain": lambda: plain(tk, grid_hw=hw)}
            if naclip is not None:
                fns["naclip"] = lambda: naclip(tk, grid_hw=hw)
            tb = interleaved(fns, reps, 1, sync=lambda: _sync(dev))
            tok = torch.randn(hw[0] * hw[1], m.cfg.embed_dim, device=dev, dtype=enc.dtype)
            th = _timeit(lambda: enc.head(tok), reps, 1, dev)
        res.update(weights=weights, feature_shape=list(feat.shape), global_shape=list(gl.shape),
                   params_backbone_M=round(sum(p.numel() for p in m.parameters()) / 1e6, 1),
                   params_head_M=round(sum(p.numel() for p in enc.head.parameters()) / 1e6, 2),
                   last_block_plain_ms=round(1e3 * statistics.median(tb["plain"]), 2),
                   head_all_patches_ms=round(1e3 * statistics.median(th), 2))
        if "naclip" in tb:
            res.update(last_block_naclip_ms=round(1e3 * statistics.median(tb["naclip"]), 2),
                       naclip_overhead_ratio=round(statistics.median(tb["naclip"]) / statistics.median(tb["plain"]), 3))
        if tmp is not None:
            tmp.cleanup()
    med = statistics.median(times)
    res.update(s_per_frame_median=round(med, 4), s_per_frame_min=round(min(times), 4),
               fps=round(1.0 / med, 3))
    return res
