"""Stage output folders: markers read back, stale folders pruned (cnnps.infra.stage_folders)."""

from __future__ import annotations

from cnnps.infra.stage_folders import prune_stale, read_json


def test_read_json_is_none_for_missing_or_broken_files(tmp_path):
    (tmp_path / "ok.json").write_text('{"key": "abc"}')
    (tmp_path / "bad.json").write_text('{"key": ')
    assert read_json(tmp_path / "ok.json") == {"key": "abc"}
    assert read_json(tmp_path / "bad.json") is None and read_json(tmp_path / "absent.json") is None


def test_prune_stale_removes_only_unwanted_folders_of_ours(tmp_path):
    def folder(name, *files):
        d = tmp_path / name
        d.mkdir()
        for f in files:
            (d / f).write_text("{}")
        return d

    keep = folder("a", "scene.json")
    stale = folder("b", "scene.json")
    stale_pending = folder("c", ".pending.json")
    user = folder("notes", "todo.txt")  # not ours: never deleted
    build = folder(".b.x1y2z3w4.tmp")  # a killed atomic write's build folder
    (tmp_path / "file.txt").write_text("x")
    removed = prune_stale(tmp_path, {"a"}, ["scene.json", ".pending.json"])
    assert removed == [stale, stale_pending]
    assert keep.is_dir() and user.is_dir() and build.is_dir() and (tmp_path / "file.txt").is_file()
    assert prune_stale(tmp_path, {"a"}, ["scene.json"], build_folders=True) == [build]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "file.txt", "notes"]
    assert prune_stale(tmp_path / "absent", set(), ["scene.json"]) == []
