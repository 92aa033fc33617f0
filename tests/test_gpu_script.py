"""`rayfronts bench gpu` / deploy/gpu_check.sh on the CPU (--device cpu --quick): every stage
of the GPU check runs (NARADIO encoder in reduced precision, both mapper presets, the
end-to-end chain over loopback Zenoh with NARADIO on the edge) and the one JSON carries the
paper's comparison. No GPU is needed, so no figure here means anything; on a CUDA machine
the same script measures them."""
import json
import subprocess
from pathlib import Path

import pytest
import torch

from apps.cli import main

ROOT = Path(__file__).resolve().parents[1]


def test_gpu_check_script_quick_on_cpu(tmp_path):
    out = tmp_path / "gpu.json"
    work = tmp_path / "work"
    r = subprocess.run(["bash", str(ROOT / "deploy" / "gpu_check.sh"), "--device", "cpu", "--quick",
                        "--dtypes", "bfloat16", "--workdir", str(work), "--json", str(out)],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    d = json.loads(out.read_text())
    assert json.loads(r.stdout) == d
    assert d["target"] == "gpu" and d["quick"] is True and d["device_info"]["device"] == "cpu"
    assert d["failed_runs"] == 0, {k: d[k] for k in ("encoder", "mapper", "e2e")}
    enc = d["encoder"]["radio_v2.5-b@64x64@bfloat16"]
    assert enc["rc"] == 0 and enc["fps"] > 0 and enc["naclip_overhead_ratio"] > 0
    sub = json.loads((work / "encoder_radio_v2.5-b_64x64_bfloat16.json").read_text())
    assert sub["device"] == "cpu" and sub["meta"]["argv"][:3] == ["rayfronts", "bench", "encoder"]
    for preset in ("throughput", "online"):
        m = d["mapper"][preset]
        assert m["rc"] == 0 and m["frames_per_s"] > 0 and m["cpu_ms_per_frame"] > 0 and m["device"] == "cpu"
    e = d["e2e"]
    assert e["rc"] == 0 and e["frames_mapped"] == 6 and e["e2e_fps"] > 0 and e["bytes_per_frame"] > 0
    e2e_sub = json.loads((work / "e2e.json").read_text())
    assert e2e_sub["settings"]["model"] == "radio_v2.5-b"
    assert "encoder.dtype=bfloat16" in e2e_sub["settings"]["edge_set"]
    assert d["paper"]["e2e_hz"] == 8.84 and d["paper"]["encoder_hz"] == 17.5
    assert d["paper_comparison"]["e2e_vs_paper"] == pytest.approx(e["e2e_fps"] / 8.84, rel=1e-2)
    assert "meta" in d and d["meta"]["machine"]["logical_cores"] >= 1


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the no-CUDA refusal")
def test_gpu_check_refuses_cuda_without_gpu(capsys):
    assert main(["bench", "gpu"]) == 2
    err = capsys.readouterr().err
    assert "CUDA is not available" in err and len(err.strip().splitlines()) == 1
    assert main(["bench", "gpu", "--device", "cpu", "--skip", "gpus"]) == 2
    assert "unknown stage" in capsys.readouterr().err
