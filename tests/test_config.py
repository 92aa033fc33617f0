"""Config loading: YAML + key=value overrides, typed, unknown keys named with a suggestion."""
from dataclasses import dataclass
from pathlib import Path

import pytest

from common.config import ConfigError, describe, field_, load_config, parse_override, section, to_dict


@dataclass
class Inner:
    vox_size: float = field_(0.3, "voxel size in metres")
    ray_tracing: bool = field_(False, "march rays through occupancy")
    names: list[str] = field_(["a"], "names")


@dataclass
class Outer:
    robot: str = field_("r1", "robot id")
    frames: int = field_(10, "frames")
    depth_limit: float | None = field_(None, "depth limit in metres")
    mapper: Inner = section(Inner, "the map")


def test_defaults_yaml_overrides(tmp_path: Path):
    p = tmp_path / "c.yaml"
    p.write_text("robot: r7\nmapper:\n  vox_size: 1\n")
    cfg = load_config(Outer, p, ["mapper.ray_tracing=true", "frames=3", "depth_limit=inf", "mapper.names=[x, y]"])
    assert cfg.robot == "r7" and cfg.frames == 3
    assert cfg.mapper.vox_size == 1.0 and isinstance(cfg.mapper.vox_size, float)
    assert cfg.mapper.ray_tracing is True
    assert cfg.depth_limit == float("inf")
    assert cfg.mapper.names == ["x", "y"]
    # defaults untouched for a fresh load (no shared mutable defaults)
    assert load_config(Outer).mapper.names == ["a"]
    assert to_dict(cfg)["mapper"]["names"] == ["x", "y"]


def test_unknown_key_names_closest(tmp_path: Path):
    with pytest.raises(ConfigError, match=r"mapper\.vox_sise.*did you mean 'mapper\.vox_size'"):
        load_config(Outer, None, ["mapper.vox_sise=0.2"])
    p = tmp_path / "c.yaml"
    p.write_text("robt: r1\n")
    with pytest.raises(ConfigError, match=r"'robt'.*did you mean 'robot'"):
        load_config(Outer, p)


def test_type_errors_are_clear():
    with pytest.raises(ConfigError, match="frames.*integer"):
        load_config(Outer, None, ["frames=abc"])
    with pytest.raises(ConfigError, match="ray_tracing.*true/false"):
        load_config(Outer, None, ["mapper.ray_tracing=3"])
    with pytest.raises(ConfigError, match="section"):
        load_config(Outer, None, ["mapper=3"])
    with pytest.raises(ConfigError, match="key=value"):
        parse_override("novalue")


def test_mapper_config_refuses_a_negative_ray_cosine_resolution():
    from mapper.service_config import load_mapper_config

    assert load_mapper_config(None, ["search.ray_cosine_resolution=0"]).search.ray_cosine_resolution == 0.0
    # exponent notation without a dot (YAML 1.1 reads it as text) is a number too
    assert load_mapper_config(None, ["search.ray_cosine_resolution=1e-3"]).search.ray_cosine_resolution == 1e-3
    for bad in ("-1e-4", "nan"):
        with pytest.raises(ConfigError, match=r"search\.ray_cosine_resolution.*>= 0"):
            load_mapper_config(None, [f"search.ray_cosine_resolution={bad}"])


def test_missing_file_and_bad_yaml(tmp_path: Path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(Outer, tmp_path / "nope.yaml")
    p = tmp_path / "bad.yaml"
    p.write_text("a: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(Outer, p)


def test_describe_lists_every_key():
    text = describe(Outer)
    for key in ["robot", "frames", "depth_limit", "mapper.vox_size", "mapper.ray_tracing", "mapper.names"]:
        assert key in text
    assert "voxel size in metres" in text
