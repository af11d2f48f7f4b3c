"""Behaviour of the content-addressed artifact store on a local folder and on memory://."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import fsspec
import pytest
from pydantic import BaseModel

from facecap.tasks.store import (
    ArtifactNotFoundError,
    ArtifactStore,
    CorruptArtifactError,
    Manifest,
    StoreWriteError,
    artifact_key,
    file_digest,
    input_key,
    open_store,
)
from facecap_core.errors import FacecapError, InputError

INPUTS = {"video": "input-" + "0" * 32}
CONFIG = {"resolution": 256, "smoothing": 0.5}
VERSION = "1"


class MeshConfig(BaseModel):
    resolution: int = 256
    smoothing: float = 0.5


def mesh_key() -> str:
    return artifact_key("mesh", INPUTS, CONFIG, VERSION)


def put_mesh(store: ArtifactStore, files, key: str | None = None) -> Manifest:
    return store.put(
        key or mesh_key(), files, stage="mesh", inputs=INPUTS, config=CONFIG, version=VERSION
    )


def stored_file_url(store_url: str, key: str, name: str) -> str:
    """Where the documented layout puts an artifact's file (used to damage it on purpose):
    the artifact folder, or on a remote backend the committing writer's folder in it."""
    folder = open_store(store_url).manifest(key).folder
    if "://" in store_url:
        assert folder is not None and folder.startswith("w-")
        return f"{store_url}/artifacts/{key}/{folder}/{name}"
    assert folder is None
    return f"{store_url}/artifacts/{key}/{name}"


@pytest.fixture(autouse=True)
def facecap_home(tmp_path, monkeypatch) -> Path:
    # Never touch the real ~/.cache/facecap from tests.
    home = tmp_path / "facecap-home"
    monkeypatch.setenv("FACECAP_HOME", str(home))
    return home


@pytest.fixture
def memory_url():
    name = f"facecap-test-{uuid.uuid4().hex}"
    yield f"memory://{name}"
    memory_fs = fsspec.filesystem("memory")
    for path in [p for p in memory_fs.store if p.startswith(f"/{name}/")]:
        del memory_fs.store[path]
    memory_fs.pseudo_dirs[:] = [d for d in memory_fs.pseudo_dirs if not d.startswith(f"/{name}")]


@pytest.fixture(params=["local", "memory"])
def store_url(request, tmp_path) -> str:
    if request.param == "local":
        return str(tmp_path / "store")
    return request.getfixturevalue("memory_url")


@pytest.fixture
def store(store_url) -> ArtifactStore:
    return open_store(store_url)


# --------------------------------------------------------------------------- keys


def test_key_is_deterministic_and_well_formed():
    key = mesh_key()
    assert key == artifact_key("mesh", dict(reversed(list(INPUTS.items()))), dict(CONFIG), "1")
    assert key.startswith("mesh-") and len(key) == len("mesh-") + 32


@pytest.mark.parametrize(
    "changed",
    [
        dict(inputs={"video": "input-" + "1" * 32}),
        dict(inputs={"clip": "input-" + "0" * 32}),
        dict(config={**CONFIG, "resolution": 512}),
        dict(config=None),
        dict(version="2"),
        dict(stage="depth"),
    ],
    ids=["input-value", "input-name", "config-value", "no-config", "version", "stage"],
)
def test_key_changes_when_anything_changes(changed):
    arguments = dict(stage="mesh", inputs=INPUTS, config=CONFIG, version=VERSION) | changed
    assert artifact_key(**arguments) != mesh_key()


def test_pydantic_config_and_equal_dict_give_the_same_key():
    assert artifact_key("mesh", INPUTS, MeshConfig(), VERSION) == mesh_key()


@pytest.mark.parametrize("stage", ["Mesh", "mesh-v2", "", "../mesh", "mesh fit"])
def test_bad_stage_names_are_rejected(stage):
    with pytest.raises(InputError):
        artifact_key(stage, INPUTS, CONFIG, VERSION)


def test_input_key_is_the_file_content_digest(tmp_path):
    video = tmp_path / "clip.mp4"
    video.write_bytes(b"frames" * 1000)
    digest = hashlib.sha256(video.read_bytes()).hexdigest()
    assert file_digest(video) == digest
    assert input_key(video) == f"input-{digest[:32]}"
    with pytest.raises(InputError):
        input_key(tmp_path / "missing.mp4")


# --------------------------------------------------------------------------- round trip


def test_put_get_read_bytes_round_trip(store, tmp_path):
    source = tmp_path / "source-depth.npy"
    source.write_bytes(b"depth" * 100)
    files = {"mesh.ply": b"ply data", "maps/depth.npy": source}

    manifest = put_mesh(store, files)

    key = mesh_key()
    assert store.exists(key)
    assert store.keys() == [key] and store.keys("mesh") == [key] and store.keys("depth") == []
    assert store.manifest(key) == manifest
    assert manifest.key == key and manifest.stage == "mesh" and manifest.version == VERSION
    assert manifest.inputs == INPUTS and manifest.config == CONFIG
    expected = {"mesh.ply": b"ply data", "maps/depth.npy": source.read_bytes()}
    for name, data in expected.items():
        assert manifest.files[name].sha256 == hashlib.sha256(data).hexdigest()
        assert manifest.files[name].size == len(data)
        assert store.read_bytes(key, name) == data

    folder = store.get(key)
    assert folder.is_dir()
    for name, data in expected.items():
        assert (folder / name).read_bytes() == data
    store.verify(key)


def test_pydantic_config_is_stored_as_plain_json(store):
    manifest = store.put(
        mesh_key(), {"a": b"x"}, stage="mesh", inputs=INPUTS, config=MeshConfig(),
        version=VERSION, meta={"faces": 12},
    )
    assert manifest.config == CONFIG and manifest.meta == {"faces": 12}


def test_put_on_an_existing_key_is_a_no_op(store, store_url):
    first = put_mesh(store, {"mesh.ply": b"first"})
    stored = stored_file_url(store_url, mesh_key(), "mesh.ply")
    mtime_before = os.stat(stored).st_mtime_ns if "://" not in store_url else None

    again = put_mesh(store, {"mesh.ply": b"second, different bytes"})

    assert again == first
    assert store.read_bytes(mesh_key(), "mesh.ply") == b"first"
    if mtime_before is not None:
        assert os.stat(stored).st_mtime_ns == mtime_before


def test_local_get_returns_the_artifact_folder(tmp_path):
    store = open_store(f"file://{tmp_path / 'store'}")
    put_mesh(store, {"mesh.ply": b"ply"})
    assert store.get(mesh_key()) == tmp_path / "store" / "artifacts" / mesh_key()
    assert repr(store) == f"ArtifactStore({str(tmp_path / 'store')!r})"


# --------------------------------------------------------------------------- failures


class ExplodingReader:
    """A file-like source that fails halfway, like a crash while reading a big input."""

    def __init__(self):
        self.calls = 0

    def read(self, size=-1):
        self.calls += 1
        if self.calls > 1:
            raise RuntimeError("simulated crash")
        return b"partial"


def assert_nothing_committed(store: ArtifactStore, store_url: str) -> None:
    assert not store.exists(mesh_key())
    assert store.keys() == []
    fs, root = fsspec.core.url_to_fs(store_url)
    assert not fs.exists(f"{root}/artifacts/{mesh_key()}")
    if "://" not in store_url:
        temp_root = Path(store_url) / ".tmp"
        assert not temp_root.exists() or list(temp_root.iterdir()) == []


def test_missing_source_file_leaves_nothing_behind(store, store_url, tmp_path):
    with pytest.raises(InputError, match="missing.npy"):
        put_mesh(store, {"mesh.ply": b"ply", "depth.npy": tmp_path / "missing.npy"})
    assert_nothing_committed(store, store_url)


def test_crash_midway_leaves_nothing_behind(store, store_url):
    with pytest.raises(RuntimeError, match="simulated crash"):
        put_mesh(store, {"mesh.ply": b"ply", "depth.npy": ExplodingReader()})
    assert_nothing_committed(store, store_url)
    # The store still works after the failed attempt.
    put_mesh(store, {"mesh.ply": b"ply"})
    assert store.keys() == [mesh_key()]


@pytest.mark.parametrize("name", ["../x", "/abs", "a/../../x", "a//b", "./a", "manifest.json"])
def test_bad_file_names_are_rejected(store, name):
    with pytest.raises(InputError):
        put_mesh(store, {name: b"x"})
    assert store.keys() == []


def test_bad_stage_or_mismatched_key_is_rejected_by_put(store):
    with pytest.raises(InputError):
        store.put(mesh_key(), {"a": b"x"}, stage="Mesh!", inputs={}, config=None, version="1")
    with pytest.raises(InputError):
        store.put(mesh_key(), {"a": b"x"}, stage="depth", inputs={}, config=None, version="1")


def test_missing_artifact_raises_not_found(store):
    with pytest.raises(ArtifactNotFoundError, match=mesh_key()):
        store.manifest(mesh_key())
    with pytest.raises(ArtifactNotFoundError):
        store.get(mesh_key())
    with pytest.raises(ArtifactNotFoundError):
        store.read_bytes(mesh_key(), "mesh.ply")
    put_mesh(store, {"mesh.ply": b"ply"})
    with pytest.raises(ArtifactNotFoundError, match="nope"):
        store.read_bytes(mesh_key(), "nope")


def test_corrupted_file_is_detected(store, store_url):
    put_mesh(store, {"mesh.ply": b"good bytes", "maps/depth.npy": b"depth"})
    with fsspec.open(stored_file_url(store_url, mesh_key(), "maps/depth.npy"), "wb") as f:
        f.write(b"DEPTH")  # same size, different content

    for check in (
        lambda: store.verify(mesh_key()),
        lambda: store.read_bytes(mesh_key(), "maps/depth.npy"),
        lambda: store.get(mesh_key()),
    ):
        with pytest.raises(CorruptArtifactError) as caught:
            check()
        message = str(caught.value)
        assert "\n" not in message
        assert mesh_key() in message and "maps/depth.npy" in message and "delete" in message
    # Unverified reads still work, for debugging.
    assert store.read_bytes(mesh_key(), "maps/depth.npy", verify=False) == b"DEPTH"


def test_a_file_checked_once_is_read_again_only_once_it_changes(tmp_path, monkeypatch):
    """A local store reads a file it checked already in this process only when its
    identity changed since (forty depth maps read the frames' artifact): a file rewritten
    with other bytes of the same size is still refused; a file modified or changed within
    the file system's timestamp granularity of its check is read on every check."""
    import facecap.tasks.store.base as base
    import facecap.tasks.store.local as local

    store = open_store(str(tmp_path / "store"))
    put_mesh(store, {"mesh.ply": b"good bytes"})
    stored = tmp_path / "store" / "artifacts" / mesh_key() / "mesh.ply"
    reads = []
    hash_stream = base.hash_stream
    monkeypatch.setattr(base, "hash_stream", lambda f: reads.append(1) or hash_stream(f))
    an_hour_ago = time.time() - 3600
    os.utime(stored, (an_hour_ago, an_hour_ago))  # modified long ago, changed just now
    changed = os.stat(stored).st_ctime_ns
    monkeypatch.setattr(local, "_now_ns", lambda: changed + local.RECENT_NS // 2)
    store.get(mesh_key())
    store.get(mesh_key())
    assert len(reads) == 2  # just changed: read each time
    monkeypatch.setattr(local, "_now_ns", lambda: changed + 3600 * 10**9)  # an hour later
    store.get(mesh_key())
    store.get(mesh_key())
    assert len(reads) == 3
    stored.write_bytes(b"evil bytes")  # the same size
    with pytest.raises(CorruptArtifactError, match="mesh.ply"):
        store.get(mesh_key())
    # The old times back: the change time is new once the clock has moved on by a tick of
    # the coarsest timestamps (10 ms: a 100 Hz kernel).
    time.sleep(0.05)
    os.utime(stored, (an_hour_ago, an_hour_ago))
    with pytest.raises(CorruptArtifactError, match="mesh.ply"):
        store.get(mesh_key())


def test_missing_stored_file_is_corruption(store, store_url):
    put_mesh(store, {"mesh.ply": b"good bytes"})
    fs, path = fsspec.core.url_to_fs(stored_file_url(store_url, mesh_key(), "mesh.ply"))
    fs.rm_file(path)
    with pytest.raises(CorruptArtifactError, match="missing"):
        store.verify(mesh_key())


def test_delete_removes_the_artifact_so_it_can_be_recomputed(store):
    put_mesh(store, {"mesh.ply": b"old"})
    store.delete(mesh_key())
    assert not store.exists(mesh_key()) and store.keys() == []
    put_mesh(store, {"mesh.ply": b"new"})
    assert store.read_bytes(mesh_key(), "mesh.ply") == b"new"
    with pytest.raises(ArtifactNotFoundError):
        store.delete(artifact_key("mesh", {}, None, "1"))


# --------------------------------------------------------------------------- local only


def test_concurrent_puts_of_one_key_commit_exactly_once(tmp_path):
    store = open_store(tmp_path / "store")
    files = {"mesh.ply": b"ply" * 10_000, "maps/depth.npy": b"depth" * 10_000}
    start = threading.Barrier(8)
    results: list[Manifest] = []
    errors: list[BaseException] = []

    def writer():
        start.wait()
        try:
            results.append(put_mesh(open_store(tmp_path / "store"), files))
        except BaseException as exc:  # noqa: BLE001 - reported by the assertion below
            errors.append(exc)

    threads = [threading.Thread(target=writer) for _ in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()

    assert errors == []
    assert len(results) == 8 and all(result == results[0] for result in results)
    assert store.keys() == [mesh_key()]
    store.verify(mesh_key())
    assert list((tmp_path / "store" / ".tmp").iterdir()) == []


def refuses_a_put_into(root: str) -> None:
    """A put into the read-only store at ``root`` fails with one line naming it, and the
    store keeps what it held."""
    store = open_store(root)
    with pytest.raises(StoreWriteError) as caught:
        put_mesh(store, {"mesh.ply": b"new"}, key=artifact_key("mesh", INPUTS, CONFIG, "2"))
    assert isinstance(caught.value.__cause__, OSError)
    assert "\n" not in str(caught.value) and str(root) in str(caught.value)
    assert store.keys() == [mesh_key()]
    assert store.read_bytes(mesh_key(), "mesh.ply") == b"kept"


def test_read_only_store_raises_store_write_error(tmp_path):
    from tests.test_bad_inputs import ROOT, bound_by_file_modes

    root = tmp_path / "store"
    put_mesh(open_store(root), {"mesh.ply": b"kept"})
    folders = [root, *(path for path in root.rglob("*") if path.is_dir())]
    for folder in folders:
        os.chmod(folder, 0o555)
    try:
        prefix = bound_by_file_modes()
        if prefix:  # root: in a process that file modes bind
            proc = subprocess.run([*prefix, sys.executable, "-c", "import sys; from "
                                   "tests.test_store import refuses_a_put_into; "
                                   "refuses_a_put_into(sys.argv[1])", str(root)],
                                  capture_output=True, text=True, cwd=ROOT, timeout=120)
            assert proc.returncode == 0, proc.stderr[-3000:]
        else:
            refuses_a_put_into(str(root))
    finally:
        for folder in folders:
            os.chmod(folder, 0o755)


def test_unwritable_location_raises_store_write_error(tmp_path):
    # A regular file where the store folder should be is refused when the store is opened;
    # one where its artifacts folder should be fails the put, even for root (one where its
    # .tmp should be is refused as planted: tests/test_own_files.py).
    blocker = tmp_path / "not-a-folder"
    blocker.write_bytes(b"")
    with pytest.raises(InputError, match="is not a folder"):
        open_store(blocker)
    (tmp_path / "store").mkdir()
    (tmp_path / "store" / "artifacts").write_bytes(b"")
    store = open_store(tmp_path / "store")
    with pytest.raises(StoreWriteError) as caught:
        put_mesh(store, {"mesh.ply": b"ply"})
    assert isinstance(caught.value, FacecapError)
    assert isinstance(caught.value.__cause__, OSError)
    assert "\n" not in str(caught.value)


# --------------------------------------------------------------------------- remote cache


def test_remote_get_downloads_into_the_cache_once(memory_url, facecap_home):
    store = open_store(memory_url)
    put_mesh(store, {"mesh.ply": b"ply", "maps/depth.npy": b"depth"})

    folder = store.get(mesh_key())

    assert folder == facecap_home / "store-cache" / mesh_key()
    assert (folder / "mesh.ply").read_bytes() == b"ply"
    assert (folder / "maps" / "depth.npy").read_bytes() == b"depth"
    marker = folder / "marker"
    marker.write_bytes(b"")  # would vanish if the second get downloaded again
    assert store.get(mesh_key()) == folder
    assert marker.exists()
    assert [p.name for p in (facecap_home / "store-cache" / ".tmp").iterdir()] == []


def test_a_planted_cache_tmp_link_is_refused_and_nothing_downloaded_behind_it(
        memory_url, facecap_home, tmp_path):
    """``$FACECAP_HOME/store-cache/.tmp`` planted as a link would have a remote artifact
    (a face) downloaded behind it: one line naming it, nothing written there."""
    from facecap.tasks.own_files import OwnFileError

    store = open_store(memory_url)
    put_mesh(store, {"mesh.ply": b"ply"})
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (facecap_home / "store-cache").mkdir(parents=True)
    (facecap_home / "store-cache" / ".tmp").symlink_to(elsewhere)
    with pytest.raises(OwnFileError, match=r"store-cache/\.tmp is a link, where facecap keeps "
                                           "a folder of its own"):
        store.get(mesh_key())
    assert not list(elsewhere.iterdir())


def test_damaged_cache_copy_is_downloaded_again(memory_url):
    store = open_store(memory_url)
    put_mesh(store, {"mesh.ply": b"ply"})
    folder = store.get(mesh_key())
    (folder / "mesh.ply").write_bytes(b"PLY")

    assert (store.get(mesh_key()) / "mesh.ply").read_bytes() == b"ply"


def test_remote_delete_drops_the_cached_copy(memory_url):
    store = open_store(memory_url)
    put_mesh(store, {"mesh.ply": b"ply"})
    folder = store.get(mesh_key())
    store.delete(mesh_key())
    assert not folder.exists()


# --------------------------------------------------------------------------- damaged manifests


@pytest.mark.parametrize("created", ["yesterday", "2026-01-01T02:00:00", "",
                                     "2026-13-01T00:00:00+00:00"],
                         ids=["words", "no time zone", "empty", "month 13"])
def test_a_manifest_whose_creation_time_is_not_a_time_is_corrupt(created, store, store_url):
    """``created`` dates an artifact for ``facecap store prune``: a manifest whose time is not
    an ISO time with its zone is damaged, reported as any damaged manifest is."""
    import json

    manifest = put_mesh(store, {"mesh.ply": b"ply"})
    doc = json.loads(manifest.model_dump_json())
    doc["created"] = created
    with fsspec.open(f"{store_url}/artifacts/{mesh_key()}/manifest.json", "w") as f:
        f.write(json.dumps(doc))
    with pytest.raises(CorruptArtifactError) as caught:
        store.manifest(mesh_key())
    assert str(caught.value).startswith(f"artifact {mesh_key()} is corrupt: file "
                                        "'manifest.json' is not a valid manifest; delete ")


def test_the_creation_time_is_kept_as_written(store):
    manifest = put_mesh(store, {"mesh.ply": b"ply"})
    assert manifest.created.endswith("+00:00")
    assert store.manifest(mesh_key()).created == manifest.created
    assert store.manifest(mesh_key()).created_at.utcoffset().total_seconds() == 0


# --------------------------------------------------------------------------- credentials


SECRET_URLS = {
    "s3://user:secret@host/bucket/x": "s3://user:***@host/bucket/x",
    "S3://user:p%40ss:w@host:9000/bucket": "S3://user:***@host:9000/bucket",
    "s3://user@host/bucket": "s3://user@host/bucket",  # no password
    "s3://bucket/prefix": "s3://bucket/prefix",
    "/data/store": "/data/store",
}


def test_a_store_url_is_shown_without_its_password(memory_url):
    """Whatever names a store in a message hides the password in its URL, in the URL and
    where a library's own message quotes it (a bucket name)."""
    from facecap.tasks.runner import store_unreachable
    from facecap.tasks.store.base import redact

    for url, shown in SECRET_URLS.items():
        assert redact(url) == shown
    assert redact('Invalid bucket name "user:secret@host": must match') == (
        'Invalid bucket name "user:***@host": must match')
    # Secret keys hold '/' and '+', passwords '@': hidden up to the authority's last '@'.
    assert redact("s3://AKIA:abc/def+ghi@host/b") == "s3://AKIA:***@host/b"
    assert redact("s3://u:p@ss@host/b x") == "s3://u:***@host/b x"
    assert redact(repr("s3://u:p@host/b")) == "'s3://u:***@host/b'"
    assert redact("at 12:30@noon") == "at 12:30@noon"  # not a URL: unchanged
    for url in ("ftp://user:secret@host/x", "s3://user:secret@host/b::x"):
        with pytest.raises(InputError) as refused:
            open_store(url)
        assert "secret" not in str(refused.value) and "user:***@host" in str(refused.value)
    assert "secret" not in repr(open_store("s3://user:secret@host/bucket"))
    secret = memory_url.replace("memory://", "memory://user:secret@")
    store = open_store(secret)
    with pytest.raises(ArtifactNotFoundError) as missing:
        store.manifest(mesh_key())
    put_mesh(store, {"mesh.ply": b"ply"})
    with pytest.raises(ArtifactNotFoundError) as no_file:
        store.read_bytes(mesh_key(), "nope")
    messages = [str(missing.value), str(no_file.value),
                str(store._corrupt(mesh_key(), "mesh.ply", "is missing")),
                str(store._write_error(mesh_key(), store.url, OSError(28, "No space left"))),
                str(store_unreachable("s3://user:secret@host/b",
                                      ValueError('Invalid bucket name "user:secret@host"'))),
                str(store_unreachable("s3://user:secret@host/b", PermissionError("denied")))]
    for message in messages:
        assert "secret" not in message and "user:***@" in message, message
    store.delete(mesh_key())


def test_open_store_picks_the_backend_and_the_interface_is_not_a_store(tmp_path):
    """``open_store`` gives the backend for the URL; the interface class itself opens
    nothing, and it does not import its backends (no import circle)."""
    import ast

    from facecap.tasks.store import ArtifactStore, LocalStore, RemoteStore

    assert type(open_store(tmp_path / "store")) is LocalStore
    assert type(open_store(f"file://{tmp_path}/store")) is LocalStore
    assert type(open_store("memory://facecap-open-store")) is RemoteStore
    with pytest.raises(TypeError, match="open_store"):
        ArtifactStore(tmp_path / "store")
    base = Path(__file__).resolve().parents[1] / "tasks" / "store" / "base.py"
    imported = {node.module for node in ast.walk(ast.parse(base.read_text()))
                if isinstance(node, ast.ImportFrom)}
    assert not imported & {"facecap.tasks.store.local", "facecap.tasks.store.remote"}
