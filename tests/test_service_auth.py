"""API keys (hashed, constant-time lookup), the service config, and the upload sniffing/decoding helpers."""

from __future__ import annotations

import hashlib

import pytest

from service.auth import KeyFileError, KeyStore, bearer_key
from service.config import ServiceConfig, parse_timeouts
from service.errors import ApiError
from service.uploads import SavedPart, check_filename, inspect_video, parse_intrinsics, sniff_container
from tests.service_helpers import SAMPLE


def test_keystore_from_file_hashes_keys(tmp_path):
    f = tmp_path / "keys"
    f.write_text("# comment\n\nalice:alice-key-0123456789abcdef\nbob:bob-key-0123456789abcdef00\n"
                 "alice:alice-second-key-0123456789\n")
    ks = KeyStore.from_file(f)
    assert ks.tenant_for("alice-key-0123456789abcdef") == "alice"
    assert ks.tenant_for("alice-second-key-0123456789") == "alice"
    assert ks.tenant_for("bob-key-0123456789abcdef00") == "bob"
    assert ks.tenant_for("bob-key-0123456789abcdef0") is None
    assert ks.tenant_for("") is None and ks.tenant_for(None) is None
    assert ks.tenants == ["alice", "bob"] and len(ks) == 3
    # only digests are kept: no plaintext key anywhere in the object
    dump = repr(vars(ks))
    assert "alice-key" not in dump
    assert hashlib.sha256(b"alice-key-0123456789abcdef").digest() in [d for d, _ in ks._entries]


@pytest.mark.parametrize("text, fragment", [
    ("alice\n", "expected 'tenant:key'"),
    ("alice:short\n", ">= 16 characters"),
    ("bad tenant:0123456789abcdefgh\n", "tenant"),
    ("a:0123456789abcdefgh\nb:0123456789abcdefgh\n", "twice"),
    ("# nothing\n", "no 'tenant:key' line"),
])
def test_keystore_rejects_bad_files(tmp_path, text, fragment):
    f = tmp_path / "keys"
    f.write_text(text)
    with pytest.raises(KeyFileError, match=fragment.replace("(", r"\(")):
        KeyStore.from_file(f)
    with pytest.raises(KeyFileError, match="cannot read"):
        KeyStore.from_file(tmp_path / "missing")


def test_generated_key_and_bearer_parsing():
    ks, key = KeyStore.generate("local")
    assert len(key) >= 32 and ks.tenant_for(key) == "local" and ks.tenant_for(key + "x") is None
    assert bearer_key(f"Bearer {key}") == key and bearer_key(f"bearer  {key} ") == key
    assert bearer_key("Basic abc") is None and bearer_key("Bearer ") is None and bearer_key(None) is None


def test_config_from_env():
    cfg = ServiceConfig.from_env({"AGG_DATA_DIR": "/srv/agg", "AGG_MAX_UPLOAD_BYTES": "1234",
                                  "AGG_PRESET_TIMEOUTS": "tiny=5,fast=60", "AGG_LEASE_S": "2.5",
                                  "AGG_WRITE_PREVIEW": "0"}, queue="q2")
    assert str(cfg.data_dir) == "/srv/agg" and cfg.max_upload_bytes == 1234 and cfg.lease_s == 2.5
    assert cfg.preset_timeouts == {"tiny": 5, "fast": 60} and cfg.presets == ["fast", "tiny"]
    assert cfg.write_preview is False and cfg.queue == "q2"
    again = ServiceConfig.from_env(cfg.to_env())
    assert again.preset_timeouts == cfg.preset_timeouts and again.lease_s == 2.5 and again.queue == "q2"
    with pytest.raises(ValueError):
        parse_timeouts("tiny=0")


def test_filename_and_field_checks():
    for ok in ("clip.mp4", "my video (1).MOV", None):
        check_filename(ok)
    for bad in ("../../etc/passwd", "a/b.mp4", "..\\x.mp4", "..", "x\x00.mp4", "/abs.mp4"):
        with pytest.raises(ApiError) as e:
            check_filename(bad)
        assert e.value.status == 400 and e.value.code == "invalid_filename"
    assert parse_intrinsics("1000,1000,640,360") == [1000, 1000, 640, 360]
    for bad in ("0,1000,640,360", "nan,1,1,1", "1,2,3", "a,b,c,d", "-5,5,1,1"):
        with pytest.raises(ApiError) as e:
            parse_intrinsics(bad)
        assert e.value.status == 422


def test_sniff_and_test_decode(tmp_path):
    data = SAMPLE.read_bytes()
    assert sniff_container(data[:400]) == "mp4"
    assert sniff_container(b"\x1a\x45\xdf\xa3" + b"\0" * 20) == "mkv"
    assert sniff_container(b"\x89PNG\r\n\x1a\n" + b"\0" * 40) is None
    good = tmp_path / "ok" / "video.upload"
    good.parent.mkdir()
    good.write_bytes(data)
    info = inspect_video(SavedPart(good, len(data)))
    assert info == {"container": "mp4", "frames": 38, "width": 1280, "height": 720, "fps": 25.0, "bytes": len(data)}
    assert (tmp_path / "ok" / "video.mp4").is_file() and not good.exists()
    cases = {"empty": (b"", 422, "empty_upload"), "text": (b"just some text, not a video" * 20, 415, "not_a_video"),
             "half": (data[: len(data) // 2], 422, "truncated_video"),
             "header_only": (data[:2000], 422, "truncated_video")}
    for name, (blob, status, code) in cases.items():
        p = tmp_path / name / "video.upload"
        p.parent.mkdir()
        p.write_bytes(blob)
        with pytest.raises(ApiError) as e:
            inspect_video(SavedPart(p, len(blob)))
        assert (e.value.status, e.value.code) == (status, code), name
        assert str(p.parent) not in e.value.message  # no server paths in client messages
