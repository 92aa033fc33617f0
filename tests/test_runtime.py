"""Pieces of the distributed runtime that need no process: the edge's one-slot queue, the
mapper's query post-processing (clusters, search volume), configs and CLIs."""
import math
import threading

import numpy as np
import pytest

from common.cones import cone_union_volume
from edge.publisher import LatestSlot
from mapper.query_answer import cluster_voxels
from tests.support.data import bfs_components


def test_latest_slot_replaces_unsent_and_counts():
    s = LatestSlot()
    s.put(1)
    s.put(2)
    s.put(3)
    assert s.replaced == 2 and s.get(0.1) == 3 and s.get(0.01) is None
    got = []
    t = threading.Thread(target=lambda: got.append(s.get(5.0)))
    t.start()
    s.put(4)
    t.join(5)
    assert got == [4] and s.replaced == 2
    s.close()
    assert s.get(1.0) is None


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cluster_voxels_matches_bfs(seed):
    rng = np.random.default_rng(seed)
    ijk = np.unique(rng.integers(-6, 6, size=(150, 3)), axis=0)
    a, b = cluster_voxels(ijk), bfs_components(ijk)
    # same partition (labels may be permuted)
    assert len(set(zip(a.tolist(), b.tolist(), strict=True))) == len(set(a.tolist())) == len(set(b.tolist()))


def test_cone_union_volume_exact_cases():
    o = np.zeros((1, 3))
    d = np.array([[1.0, 0, 0]])
    exact = math.pi * 50 ** 3 * math.tan(math.radians(20)) ** 2 / 3
    assert cone_union_volume(o, d, 20, 50, 1.0) == pytest.approx(exact)
    # two far-apart identical cones: twice the volume (grid estimate)
    o2 = np.array([[0.0, 0, 0], [0.0, 500, 0]])
    v2 = cone_union_volume(o2, np.repeat(d, 2, 0), 20, 50, 0.5, max_cells=2_000_000)
    assert v2 == pytest.approx(2 * exact, rel=0.05)
    # two identical cones: the union is one cone
    v1 = cone_union_volume(np.zeros((2, 3)), np.repeat(d, 2, 0), 20, 50, 0.5, max_cells=2_000_000)
    assert v1 == pytest.approx(exact, rel=0.05)


def test_reject_reason_codes():
    from common.wire import WireError, decode_frame
    from mapper.ingest import reject_reason

    reasons = set()
    for bad in (b"", b"\x05\x00\x00\x00abc", b"\xff" * 40):
        with pytest.raises(WireError) as e:
            decode_frame(bad)
        reasons.add(reject_reason(e.value))
    assert all(r and " " not in r and len(r) <= 40 for r in reasons)


def test_cli_help_lists_every_config_key(capsys):
    from apps.cli import main
    from common.config import all_keys
    from edge.config import EdgeConfig
    from mapper.service_config import MapperConfig

    for cmd, schema in (("edge", EdgeConfig), ("mapper", MapperConfig)):
        with pytest.raises(SystemExit):
            main([cmd, "--help"])
        out = capsys.readouterr().out
        for k in all_keys(schema):
            assert k in out, f"{cmd} --help lacks {k}"


def test_mapper_config_preset_and_overrides():
    from common.config import ConfigError
    from mapper.service_config import load_mapper_config
    from semantic_map.config import PRESETS

    cfg = load_mapper_config(None, ["preset=online", "map.vox_size=0.7", "queues.per_robot=3"])
    assert cfg.map.vox_size == 0.7 and cfg.queues.per_robot == 3
    assert cfg.map.angle_bin_size == PRESETS["online"]["angle_bin_size"]
    with pytest.raises(ConfigError, match="preset"):
        load_mapper_config(None, ["preset=nope"])
    with pytest.raises(ConfigError, match="did you mean"):
        load_mapper_config(None, ["queues.per_robott=3"])
