from __future__ import annotations

import hashlib
import pickle
import zipfile

import pytest
import torch

from cnnps.infra.errors import InputError
from cnnps.models.checkpoint import (
    file_sha256,
    load_checkpoint,
    read_checkpoint,
    save_checkpoint,
    state_digest,
)
from cnnps.models.network import ARCH_VERSION, CNNPS


class Evil:
    """Unpickling this would run code; weights_only loading must refuse it."""

    def __reduce__(self):
        return (print, ("pwned",))


@pytest.fixture(scope="module")
def model() -> CNNPS:
    torch.manual_seed(0)
    return CNNPS().eval()


@pytest.fixture(scope="module")
def maps() -> torch.Tensor:
    g = torch.Generator().manual_seed(5)
    return torch.rand(32, 1, 32, 32, generator=g) * (torch.rand(32, 1, 32, 32, generator=g) < 0.1)


def _angles_deg(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.rad2deg(torch.acos((a * b).sum(1).clamp(-1, 1)))


def test_round_trip_fp32_identical(tmp_path, model, maps):
    path = save_checkpoint(tmp_path / "model.pt", model, {"lr": 1e-3}, {"steps": 12, "val_mean_deg": 3.5})
    loaded, config, meta = load_checkpoint(path)
    assert config == {"lr": 1e-3, "w": 32, "dropout": 0.2, "in_channels": 1, "arch_version": ARCH_VERSION}
    assert meta == {"steps": 12, "val_mean_deg": 3.5}
    assert not loaded.training
    assert next(loaded.parameters()).dtype == torch.float32
    with torch.no_grad():
        assert torch.equal(model(maps), loaded(maps))
    assert 10.0e6 < path.stat().st_size < 11.0e6  # 2.65 M float32
    assert [p.name for p in tmp_path.iterdir()] == ["model.pt"]  # no temp files left


def test_round_trip_fp16_storage(tmp_path, model, maps):
    path = save_checkpoint(tmp_path / "half.pt", model, {}, {}, half=True)
    assert 5.0e6 < path.stat().st_size < 5.6e6  # well under the 12 MB shipping limit
    assert read_checkpoint(path)["weights_dtype"] == "float16"
    loaded, _, _ = load_checkpoint(path)
    assert next(loaded.parameters()).dtype == torch.float32
    with torch.no_grad():
        err = _angles_deg(model(maps), loaded(maps))
    # measured: max ~0.01 deg for he-initialised weights
    assert err.max() < 0.1
    assert err.max() > 0  # it really was rounded


def test_config_disagreeing_with_model_is_refused(tmp_path, model):
    with pytest.raises(ValueError, match="disagrees"):
        save_checkpoint(tmp_path / "x.pt", model, {"w": 64}, {})
    with pytest.raises(ValueError, match="JSON-like"):
        save_checkpoint(tmp_path / "x.pt", model, {}, {"path": tmp_path})
    assert not any(tmp_path.iterdir())


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="not found") as info:
        load_checkpoint(tmp_path / "nope.pt")
    assert info.value.path == tmp_path / "nope.pt"


@pytest.mark.filterwarnings("ignore:Detected pickle protocol")
def test_pickle_with_arbitrary_objects_is_refused(tmp_path, capsys):
    path = tmp_path / "evil.pt"
    torch.save({"format": "cnnps-checkpoint", "payload": Evil()}, path)
    with pytest.raises(InputError, match="refused for safety"):
        load_checkpoint(path)
    assert "pwned" not in capsys.readouterr().out
    plain = tmp_path / "plain.pkl"
    plain.write_bytes(pickle.dumps(Evil()))
    with pytest.raises(InputError):
        load_checkpoint(plain)
    assert "pwned" not in capsys.readouterr().out


@pytest.mark.parametrize("damage", ["truncate", "garbage", "empty", "flip"])
def test_damaged_file(tmp_path, model, damage):
    path = save_checkpoint(tmp_path / "model.pt", model, {}, {}, half=True)
    data = path.read_bytes()
    if damage == "truncate":
        path.write_bytes(data[: len(data) // 2])
    elif damage == "garbage":
        path.write_bytes(b"this is not a checkpoint" * 100)
    elif damage == "empty":
        path.write_bytes(b"")
    else:  # corrupt the stored bytes of the big weight inside the zip: crc check fails
        with zipfile.ZipFile(path) as zf:
            info = max(zf.infolist(), key=lambda i: i.file_size)
        start = info.header_offset + 30 + len(info.filename) + len(info.extra) + 1000
        buf = bytearray(data)
        buf[start:start + 64] = bytes(64)
        path.write_bytes(bytes(buf))
    with pytest.raises(InputError) as info:
        load_checkpoint(path)
    assert str(path) in str(info.value)


def _rewrite(path, out, edit):
    payload = torch.load(path, weights_only=True)
    edit(payload)
    torch.save(payload, out)
    return out


def test_wrong_arch_version(tmp_path, model):
    path = save_checkpoint(tmp_path / "model.pt", model, {}, {})
    bad = _rewrite(path, tmp_path / "old.pt", lambda p: p["config"].update(arch_version=ARCH_VERSION + 1))
    with pytest.raises(InputError, match="architecture version"):
        load_checkpoint(bad)


def test_config_weights_mismatch(tmp_path, model):
    path = save_checkpoint(tmp_path / "model.pt", model, {}, {})
    bad = _rewrite(path, tmp_path / "w16.pt", lambda p: p["config"].update(w=16))
    with pytest.raises(InputError, match="do not match the config"):
        load_checkpoint(bad)
    bad = _rewrite(path, tmp_path / "odd.pt", lambda p: p["config"].update(w=31))
    with pytest.raises(InputError, match="cannot rebuild"):
        load_checkpoint(bad)
    bad = _rewrite(path, tmp_path / "nan.pt", lambda p: p["state_dict"]["fc2.bias"].fill_(float("nan")))
    with pytest.raises(InputError, match="SHA-256"):
        load_checkpoint(bad)

    def nan_with_digest(p):
        p["state_dict"]["fc2.bias"].fill_(float("nan"))
        p["weights_sha256"] = state_digest(p["state_dict"])

    bad = _rewrite(path, tmp_path / "nan2.pt", nan_with_digest)
    with pytest.raises(InputError, match="fc2.bias"):
        load_checkpoint(bad)
    bad = _rewrite(path, tmp_path / "nofmt.pt", lambda p: p.pop("format"))
    with pytest.raises(InputError, match="not a cnnps checkpoint"):
        load_checkpoint(bad)


def test_file_sha256(tmp_path):
    path = tmp_path / "blob.bin"
    data = bytes(range(256)) * 5000
    path.write_bytes(data)
    assert file_sha256(path) == hashlib.sha256(data).hexdigest()
    with pytest.raises(InputError):
        file_sha256(tmp_path / "missing.bin")


def test_state_digest_ignores_memory_format():
    # a channels_last model (what training uses) has the same weights, hence the same digest
    model = CNNPS()
    plain = state_digest(model.state_dict())
    model = model.to(memory_format=torch.channels_last)
    assert state_digest(model.state_dict()) == plain


def test_unforeseen_load_failure_names_the_file(tmp_path, monkeypatch):
    import cnnps.models.checkpoint as ck

    def boom(path, device):
        raise ValueError("something unforeseen")

    monkeypatch.setattr(ck, "_load_checkpoint", boom)
    with pytest.raises(InputError, match="could not load model .ValueError: something unforeseen") as info:
        ck.load_checkpoint(tmp_path / "m.pt")
    assert info.value.path == tmp_path / "m.pt"


def test_checkpoint_bytes_depend_only_on_the_content(tmp_path, model):
    a = save_checkpoint(tmp_path / "a" / "model.pt", model, {}, {"steps": 1})
    b = save_checkpoint(tmp_path / "b" / "other.pt", model, {}, {"steps": 1})
    assert a.read_bytes() == b.read_bytes()  # no temporary file name inside the zip


def _member_data(path, pick):
    """(start, size) of a zip member's data in the file (after its local header)."""
    raw = path.read_bytes()
    with zipfile.ZipFile(path) as zf:
        info = pick(zf.infolist())
    o = info.header_offset
    start = o + 30 + int.from_bytes(raw[o + 26:o + 28], "little") + int.from_bytes(raw[o + 28:o + 30], "little")
    return start, info.compress_size


def _flip(path, at):
    buf = bytearray(path.read_bytes())
    buf[at] ^= 0x01
    path.write_bytes(bytes(buf))


def test_a_flip_in_the_pickled_config_or_meta_is_caught_by_the_crc(tmp_path, model):
    """The weights digest does not cover config and meta; the members' CRC-32 does."""
    path = save_checkpoint(tmp_path / "model.pt", model, {}, {"steps": 12, "note": "x" * 40})
    start, size = _member_data(path, lambda infos: next(i for i in infos if i.filename.endswith("data.pkl")))
    _flip(path, start + size - 60)  # inside the pickle, among the meta strings
    with pytest.raises(InputError, match="CRC-32") as info:
        load_checkpoint(path)
    assert info.value.path == path


def test_sha256_file_covers_every_byte(tmp_path, model):
    from cnnps.models.checkpoint import sha256_file_path, write_sha256_file

    path = save_checkpoint(tmp_path / "model.pt", model, {}, {"steps": 1})
    side = write_sha256_file(path)
    assert side == sha256_file_path(path) == tmp_path / "model.pt.sha256"
    assert side.read_text() == f"{hashlib.sha256(path.read_bytes()).hexdigest()}  model.pt\n"  # sha256sum -c format
    load_checkpoint(path)
    _flip(path, 10)  # the first member's modification time: no other check reads it
    side.rename(tmp_path / "kept")
    load_checkpoint(path)  # harmless without the checksum file (the loaded checkpoint is the same)
    (tmp_path / "kept").rename(side)
    with pytest.raises(InputError, match="model.pt.sha256") as info:
        load_checkpoint(path)
    assert info.value.path == path
    side.write_text("not a checksum\n")
    with pytest.raises(InputError, match="not a SHA-256 checksum file") as info:
        load_checkpoint(path)
    assert info.value.path == side
