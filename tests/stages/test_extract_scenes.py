"""The extract stage's ``scenes`` selection: which rendered scenes it reads, in both
layouts, outside every key while empty, outside the per-scene keys when set."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from cnnps.infra.errors import ConfigError
from cnnps.infra.hashing import stable_hash
from cnnps.io.shards import load_manifest, manifest_digest
from cnnps.stages import extract
from cnnps.stages.extract import Params
from tests.support.renders import make_render_dir, make_scene

SMALL = dict(min_lights=10, max_lights=40, rotations=4, rows_per_group=500, rows_per_shard=1500, chunk_pixels=100)
MAPS = dict(val_fraction=0.34, seed=7, pixels_per_scene=40, **SMALL)
OBS = dict(layout="observations", val_fraction=0.34, seed=7)
# recorded with the stage before it had a ``scenes`` key (same fixtures): the default
# output, and so the train stage's run key, must not move
PINNED = {
    # the maps manifest less its shards' bytes and SHA-256 (those depend on the Parquet writer)
    "maps_manifest": "64b3215fd18d7dfa954918af8566edfcdcb394b79c232b92ee7f8bbc67e4a19e",
    "maps_markers": {
        "scene-s00.json": "70d96444d396b44b1c427e36cfc6891f",
        "scene-s01.json": "c1b306d8b56eceaca25ee056d476bfde",
        "scene-s02.json": "fa6d01e7eec3c6834f2534c5e9974472",
    },
    "obs_digest": "a575c8aeceb75bd103b315c402f58e73bf71fa017ffb28db4e2512ed079adc31",
}
IDS = ["ball-0-a1", "ball-1-b2", "ball-2-c3", "cube-0-d4", "cube-1-e5", "cube-2-f6"]


def _render(data: Path, size: int = 24, m: int = 60) -> Path:
    """Six scenes named as the render stage names them, <source>-<view>-<hash>."""
    for i, sid in enumerate(IDS):
        make_scene(data / "render", sid, seed=200 + i, size=size, m=m, view_id=sid.rsplit("-", 1)[0])
    return data


def _stamps(out: Path, pattern: str) -> dict[str, int]:
    return {p.name: p.stat().st_mtime_ns for p in out.glob(pattern)}


def test_default_output_is_unchanged(tmp_path):
    assert "scenes" not in Params().manifest_params() and "scenes" not in Params().row_key()
    maps = make_render_dir(tmp_path / "maps", n_scenes=3)
    extract.run(Params(**MAPS), maps)
    out = maps / "extract"
    man = load_manifest(out)
    assert stable_hash({k: v for k, v in man.items() if k not in ("shards", "checksum")}) == PINNED["maps_manifest"]
    assert {p.name: json.loads(p.read_text())["key"] for p in out.glob("scene-*.json")} == PINNED["maps_markers"]
    obs = make_render_dir(tmp_path / "obs", n_scenes=3, size=20, m=30)
    extract.run(Params(**OBS), obs)
    assert manifest_digest(obs / "extract") == PINNED["obs_digest"]


def test_selection_reads_exactly_the_selected_scenes_and_keeps_scene_keys(tmp_path, capsys):
    data = _render(tmp_path)
    out = data / "extract"
    extract.run(Params(**MAPS), data)
    every = load_manifest(out)
    keys = {sid: rec["key"] for sid, rec in every["scenes"].items()}
    shard_sha = {s["file"]: s["sha256"] for s in every["shards"]}
    stamps = _stamps(out, "shard-*.parquet")

    extract.run(Params(scenes=["*-1-*", "*-0-*"], **MAPS), data)
    assert "extract: 4 of 6 rendered scenes selected by extract.scenes" in capsys.readouterr().out
    man = load_manifest(out)
    chosen = ["ball-0-a1", "ball-1-b2", "cube-0-d4", "cube-1-e5"]
    assert sorted(man["scenes"]) == chosen
    assert sorted(man["train_scenes"] + man["val_scenes"]) == chosen  # the split is within the selection
    assert man["params"]["scenes"] == ["*-0-*", "*-1-*"]  # in the manifest: the train run key moves
    assert manifest_digest(out) != every["checksum"]
    # per-scene keys and files are the selection's-independent ones: reused, not rewritten
    assert {sid: rec["key"] for sid, rec in man["scenes"].items()} == {s: keys[s] for s in chosen}
    assert all(shard_sha[s["file"]] == s["sha256"] for s in man["shards"])
    assert _stamps(out, "shard-*.parquet") == {
        n: t for n, t in stamps.items() if n[len("shard-") :].rsplit("-", 1)[0] in chosen
    }
    # scenes outside the selection leave the output (the stale-file rule)
    assert sorted(p.name[len("scene-") : -len(".json")] for p in out.glob("scene-*.json")) == chosen

    # another selection: the scenes it shares are reused as they are
    kept = _stamps(out, "shard-ball-0-*")
    extract.run(Params(scenes=["ball-0-*", "ball-2-*"], val_scenes=["ball-2-c3"], **MAPS), data)
    man = load_manifest(out)
    assert sorted(man["scenes"]) == ["ball-0-a1", "ball-2-c3"] and man["val_scenes"] == ["ball-2-c3"]
    assert _stamps(out, "shard-ball-0-*") == kept


def test_observations_layout_honours_the_selection(tmp_path):
    data = _render(tmp_path, size=20, m=30)
    out = data / "extract"
    extract.run(Params(scenes=["*-0-*"], **OBS), data)
    assert sorted(p.name for p in out.glob("obs-*.cnnobs")) == ["obs-ball-0-a1.cnnobs", "obs-cube-0-d4.cnnobs"]
    stamps = _stamps(out, "obs-*.cnnobs")
    extract.run(Params(scenes=["*-0-*", "cube-*"], **OBS), data)
    man = load_manifest(out)
    assert sorted(man["scenes"]) == ["ball-0-a1", "cube-0-d4", "cube-1-e5", "cube-2-f6"]
    assert man["params"]["scenes"] == ["*-0-*", "cube-*"] and man["layout"] == "observations"
    after = _stamps(out, "obs-*.cnnobs")
    assert {n: after[n] for n in stamps} == stamps and len(after) == 4


def test_a_pattern_matching_no_scene_is_one_line_naming_it(tmp_path):
    data = _render(tmp_path)
    with pytest.raises(ConfigError) as err:
        extract.run(Params(scenes=["*-0-*", "*-9-*"], **MAPS), data)
    assert str(err.value) == "extract.scenes pattern '*-9-*' matches none of the 6 rendered scenes"
    assert not (data / "extract").exists()  # refused before anything is written
    with pytest.raises(ConfigError, match="among those extract.scenes selects"):
        extract.run(Params(scenes=["*-0-*"], val_scenes=["ball-1-b2"], **MAPS), data)
    with pytest.raises(ConfigError, match="extract.scenes"):
        Params(scenes=["*-0-*", ""])
    assert Params(scenes="*-0-*").scenes == ("*-0-*",)
