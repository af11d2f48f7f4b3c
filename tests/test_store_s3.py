"""The artifact store on S3, as the compose stack runs it on MinIO.

One module on purpose (~500 lines): every test shares one in-process S3 server and its
environment, set up once.

A real S3 server runs in this process (moto's ThreadedMotoServer, over HTTP on 127.0.0.1);
the store finds it only through the environment, as the workers do: credentials in
AWS_ACCESS_KEY_ID / AWS_SECRET_ACCESS_KEY and the endpoint in AWS_ENDPOINT_URL_S3 (botocore,
hence s3fs) or FSSPEC_S3_ENDPOINT_URL (fsspec). The behaviour shared by every backend (keys,
round trips, bad names, the remote cache) is tested on memory:// in test_store.py; this file
covers what only a real S3 endpoint shows: objects as S3 stores them, uploads left without
a manifest, the server going away and coming back.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import subprocess
import sys
import threading
import uuid
from pathlib import Path

import boto3
import pytest
import s3fs
import yaml
from moto.server import ThreadedMotoServer

from facecap.tasks.store import (
    ArtifactNotFoundError,
    ArtifactStore,
    CorruptArtifactError,
    StoreWriteError,
    artifact_key,
    open_store,
)
from facecap_core.errors import InputError

ROOT = Path(__file__).resolve().parents[1]
BUCKET = "facecap-store-test"
INPUTS = {"video": "input-" + "0" * 32}
CONFIG = {"resolution": 256}
# Keys, credentials and endpoint of the test server; nothing else of the caller's AWS setup.
CREDENTIALS = {"AWS_ACCESS_KEY_ID": "test-access-key", "AWS_SECRET_ACCESS_KEY": "test-secret"}


class LocalS3:
    """moto's S3 server on a fixed loopback port that can be stopped and started again.

    moto keeps its buckets in this process, so objects survive a restart: a stop is an
    outage of the endpoint, not a loss of data.
    """

    def __init__(self) -> None:
        self.port = 0
        self._server: ThreadedMotoServer | None = None

    def start(self) -> None:
        self._server = ThreadedMotoServer(ip_address="127.0.0.1", port=self.port, verbose=False)
        self._server.start()
        self.port = self._server.get_host_and_port()[1]

    def stop(self) -> None:
        self._server.stop()
        # stop() only ends the serving loop; closing the socket makes clients get
        # "connection refused" at once instead of waiting for a read timeout.
        self._server._server.server_close()
        self._server = None

    @property
    def running(self) -> bool:
        return self._server is not None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"


@pytest.fixture(scope="module")
def s3():
    logging.getLogger("werkzeug").setLevel(logging.ERROR)  # one log line per request otherwise
    server = LocalS3()
    server.start()
    with pytest.MonkeyPatch.context() as patch:
        for name in [n for n in os.environ if n.startswith(("AWS_", "FSSPEC_S3"))]:
            patch.delenv(name)
        for name, value in CREDENTIALS.items():
            patch.setenv(name, value)
        patch.setenv("AWS_ENDPOINT_URL_S3", server.url)
        # botocore retries a refused connection 4 times with backoff (~10 s) by default; one
        # attempt keeps the outage tests fast. The compose workers keep retries on.
        patch.setenv("AWS_MAX_ATTEMPTS", "1")
        s3fs.S3FileSystem.clear_instance_cache()  # instances keep the endpoint they were made with
        boto3.client("s3", region_name="us-east-1").create_bucket(Bucket=BUCKET)
        yield server
        s3fs.S3FileSystem.clear_instance_cache()
    if server.running:
        server.stop()


@pytest.fixture(autouse=True)
def facecap_home(tmp_path, monkeypatch) -> Path:
    home = tmp_path / "facecap-home"
    monkeypatch.setenv("FACECAP_HOME", str(home))
    return home


@pytest.fixture
def prefix() -> str:
    return f"store-{uuid.uuid4().hex[:12]}"


@pytest.fixture
def store(s3, prefix) -> ArtifactStore:
    return open_store(f"s3://{BUCKET}/{prefix}")


@pytest.fixture
def bucket(s3):
    """A plain boto3 view of the bucket: what is really on the server, bypassing the store."""
    return boto3.client("s3", region_name="us-east-1")


def mesh_key(version: str = "1") -> str:
    return artifact_key("mesh", INPUTS, CONFIG, version)


def put_mesh(store: ArtifactStore, files, version: str = "1"):
    return store.put(mesh_key(version), files, stage="mesh", inputs=INPUTS, config=CONFIG,
                     version=version)


def objects(bucket, prefix: str) -> dict[str, bytes]:
    listed = bucket.list_objects_v2(Bucket=BUCKET, Prefix=f"{prefix}/").get("Contents", [])
    return {
        item["Key"].removeprefix(f"{prefix}/"):
            bucket.get_object(Bucket=BUCKET, Key=item["Key"])["Body"].read()
        for item in listed
    }


def one_line(error: BaseException) -> str:
    message = str(error)
    assert "\n" not in message
    return message


# --------------------------------------------------------------------------- round trip


def test_round_trip_through_the_endpoint_from_the_environment(store, bucket, prefix, tmp_path,
                                                                facecap_home):
    depth = tmp_path / "depth.npy"
    depth.write_bytes(os.urandom(3 * 1024 * 1024 + 17))  # several 1 MiB chunks, odd tail
    manifest = put_mesh(store, {"mesh.ply": b"ply data", "maps/depth.npy": depth})

    key = mesh_key()
    assert store.url == f"s3://{BUCKET}/{prefix}"
    # The objects are on the S3 server, in the documented layout, byte for byte: the
    # manifest in the artifact folder, the files in the committing writer's folder.
    stored = objects(bucket, prefix)
    writer = manifest.folder
    assert re.fullmatch(r"w-[0-9a-f]{32}", writer)
    assert set(stored) == {f"artifacts/{key}/manifest.json",
                           *(f"artifacts/{key}/{writer}/{name}"
                             for name in ("mesh.ply", "maps/depth.npy"))}
    assert stored[f"artifacts/{key}/{writer}/maps/depth.npy"] == depth.read_bytes()
    assert manifest.files["maps/depth.npy"].sha256 == hashlib.sha256(depth.read_bytes()).hexdigest()

    assert store.exists(key) and store.keys() == [key] and store.keys("mesh") == [key]
    assert store.keys("depth") == []
    store.verify(key)
    assert store.read_bytes(key, "mesh.ply") == b"ply data"
    folder = store.get(key)
    assert folder == facecap_home / "store-cache" / key
    assert (folder / "maps" / "depth.npy").read_bytes() == depth.read_bytes()

    # Another worker's store object sees the same committed artifact.
    other = open_store(f"s3://{BUCKET}/{prefix}")
    assert other.manifest(key) == manifest


def test_keys_of_an_empty_or_absent_prefix_are_empty(store):
    assert store.keys() == []
    assert not store.exists(mesh_key())


def test_a_missing_bucket_is_a_store_write_error(s3):
    store = open_store(f"s3://no-such-bucket-{uuid.uuid4().hex[:8]}/artifacts")
    with pytest.raises(StoreWriteError) as caught:
        put_mesh(store, {"mesh.ply": b"ply"})
    assert "bucket" in one_line(caught.value)


def test_the_results_link_is_a_presigned_url_of_the_page(store, prefix, tmp_path):
    """A capture run whose store is S3 links its UI page to its results page in the store:
    a URL that anyone who has it can open in a browser (as a page, not a download), without
    credentials, for RESULTS_LINK_SECONDS."""
    import time
    import urllib.parse
    import urllib.request

    from facecap.flows.ui import RESULTS_LINK_SECONDS, results_link
    from facecap.pages.stored import PAGE_NAME, store_page

    page = b"<!doctype html><title>the page</title>"
    report = {"store": store.url, "stages": {"fitting": {"key": mesh_key()}}}
    key = store_page(store, report, page)
    link, where = results_link({**report, "page": {"key": key}}, tmp_path / "out")
    assert where == "its page, for 24 h" and RESULTS_LINK_SECONDS == 24 * 3600
    url = urllib.parse.urlsplit(link)
    query = urllib.parse.parse_qs(url.query)
    assert url.path == f"/{BUCKET}/{prefix}/artifacts/{key}/{store.manifest(key).folder}/{PAGE_NAME}"
    if "X-Amz-Expires" in query:  # signature version 4: seconds from signing
        assert query["X-Amz-Expires"] == [str(RESULTS_LINK_SECONDS)]
    else:  # botocore's default for S3 in us-east-1 without a configured version: a deadline
        assert abs(int(query["Expires"][0]) - time.time() - RESULTS_LINK_SECONDS) < 60
    with urllib.request.urlopen(link, timeout=10) as answer:  # no credentials but the URL's
        assert answer.read() == page
        assert answer.headers["Content-Type"] == "text/html; charset=utf-8"
    with pytest.raises(ValueError, match="7 days"):
        store.presigned_url(key, PAGE_NAME, 8 * 24 * 3600)
    with pytest.raises(ArtifactNotFoundError, match="no file 'cloud.ply'"):
        store.presigned_url(key, "cloud.ply", 60)
    # Without a page (an artifact gone, a run from before pages): the page on disk.
    gone = {**report, "page": {"key": "page-" + "0" * 32}}
    assert results_link(gone, tmp_path / "out")[0] == (
        (tmp_path / "out").resolve() / PAGE_NAME).as_uri()


# --------------------------------------------------------------------------- damage


@pytest.mark.parametrize("damaged", [b"PLY DATA", b"ply data, and more"],
                         ids=["same-size", "other-size"])
def test_a_corrupt_object_is_detected(store, bucket, prefix, damaged):
    put_mesh(store, {"mesh.ply": b"ply data"})
    key = mesh_key()
    writer = store.manifest(key).folder
    bucket.put_object(Bucket=BUCKET, Key=f"{prefix}/artifacts/{key}/{writer}/mesh.ply",
                      Body=damaged)

    for check in (lambda: store.verify(key), lambda: store.read_bytes(key, "mesh.ply"),
                  lambda: store.get(key)):
        with pytest.raises(CorruptArtifactError) as caught:
            check()
        message = one_line(caught.value)
        assert key in message and "mesh.ply" in message
        assert f"delete s3://{BUCKET}/{prefix}/artifacts/{key}" in message


def test_a_corrupt_manifest_is_detected(store, bucket, prefix):
    put_mesh(store, {"mesh.ply": b"ply data"})
    key = mesh_key()
    bucket.put_object(Bucket=BUCKET, Key=f"{prefix}/artifacts/{key}/manifest.json",
                      Body=b'{"key": "truncated')
    with pytest.raises(CorruptArtifactError, match="manifest.json"):
        store.manifest(key)


@pytest.mark.parametrize("name", ["../../escaped.txt", "/tmp/escaped.txt", "a/../../x"])
def test_a_manifest_cannot_steer_a_download_out_of_the_cache(store, bucket, prefix, name,
                                                            facecap_home, tmp_path):
    """Whoever can write the bucket (a shared S3 key) edits a manifest so that a file name
    leads out of the artifact: the reader refuses the manifest and writes nothing."""
    put_mesh(store, {"mesh.ply": b"ply data"})
    key = mesh_key()
    manifest_key = f"{prefix}/artifacts/{key}/manifest.json"
    doc = json.loads(bucket.get_object(Bucket=BUCKET, Key=manifest_key)["Body"].read())
    doc["files"][name] = doc["files"].pop("mesh.ply")
    bucket.put_object(Bucket=BUCKET, Key=manifest_key, Body=json.dumps(doc).encode())
    stored = f"{prefix}/artifacts/{key}/{doc['folder']}/mesh.ply"
    bucket.put_object(Bucket=BUCKET, Key=stored.replace("mesh.ply", name), Body=b"ply data")
    with pytest.raises(CorruptArtifactError, match="names a file outside its artifact"):
        store.get(key)
    assert not list(tmp_path.rglob("escaped.txt")) and not Path("/tmp/escaped.txt").exists()


def test_a_missing_artifact_or_object_raises_the_stores_errors(store, bucket, prefix):
    key = mesh_key()
    for call in (lambda: store.manifest(key), lambda: store.get(key),
                 lambda: store.read_bytes(key, "mesh.ply"), lambda: store.delete(key)):
        with pytest.raises(ArtifactNotFoundError) as caught:
            call()
        assert key in one_line(caught.value)

    put_mesh(store, {"mesh.ply": b"ply data", "texture.png": b"png"})
    writer = store.manifest(key).folder
    bucket.delete_object(Bucket=BUCKET, Key=f"{prefix}/artifacts/{key}/{writer}/texture.png")
    with pytest.raises(CorruptArtifactError, match="texture.png' is missing"):
        store.verify(key)
    with pytest.raises(CorruptArtifactError, match="is missing"):
        store.get(key)


def test_delete_removes_every_object(store, bucket, prefix):
    put_mesh(store, {"mesh.ply": b"ply", "maps/a.npy": b"a"})
    folder = store.get(mesh_key())
    store.delete(mesh_key())
    assert objects(bucket, prefix) == {}
    assert not folder.exists()
    assert not store.exists(mesh_key())


def test_an_upload_without_manifest_is_invisible_and_is_completed_by_the_next_put(
        store, bucket, prefix):
    # What a writer that died mid-upload leaves: files in its own folder, no manifest.
    key = mesh_key()
    dead = f"w-{uuid.uuid4().hex}"
    bucket.put_object(Bucket=BUCKET, Key=f"{prefix}/artifacts/{key}/{dead}/mesh.ply",
                      Body=b"half")
    assert not store.exists(key)
    assert store.keys() == []
    with pytest.raises(ArtifactNotFoundError):
        store.get(key)

    manifest = put_mesh(store, {"mesh.ply": b"whole mesh"})
    assert manifest.folder != dead
    assert store.read_bytes(key, "mesh.ply") == b"whole mesh"
    store.verify(key)


# --------------------------------------------------------------------------- outages


def store_calls(store: ArtifactStore) -> dict:
    """Every store operation a task makes, on the committed artifact ``mesh_key()``."""
    return {
        "exists": lambda: store.exists(mesh_key()),
        "manifest": lambda: store.manifest(mesh_key()).key,
        "verify": lambda: store.verify(mesh_key()),
        "read_bytes": lambda: store.read_bytes(mesh_key(), "mesh.ply"),
        "get": lambda: (store.get(mesh_key()) / "mesh.ply").read_bytes(),
        "keys": lambda: store.keys(),
        "put": lambda: put_mesh(store, {"mesh.ply": b"v2"}, version="2").key,
    }


def test_an_outage_raises_instead_of_answering_and_calls_succeed_once_it_is_over(s3, store):
    put_mesh(store, {"mesh.ply": b"ply data"})
    s3.stop()
    try:
        for name, call in store_calls(store).items():
            with pytest.raises(Exception) as caught:
                call()
            # Never mistaken for an absent or damaged artifact, or for bad input: a task
            # must not recompute, delete or give up because the endpoint was away.
            assert not isinstance(
                caught.value, (ArtifactNotFoundError, CorruptArtifactError, InputError)
            ), f"{name}: {caught.value!r}"
            # The message says where: the endpoint, or the store's bucket.
            assert re.search(rf"127\.0\.0\.1|{BUCKET}", str(caught.value)), repr(caught.value)
    finally:
        s3.start()
    results = {name: call() for name, call in store_calls(store).items()}
    assert results["exists"] is True and results["read_bytes"] == b"ply data"
    assert results["get"] == b"ply data" and results["manifest"] == mesh_key()
    assert sorted(results["keys"]) == [mesh_key()]  # listed before the "put" call
    assert store.keys() == sorted([mesh_key(), mesh_key("2")])


class StopsServer:
    """A file source whose first read takes the S3 server down: an outage mid-put."""

    def __init__(self, s3: LocalS3) -> None:
        self.s3 = s3

    def read(self, size: int = -1) -> bytes:
        if self.s3.running:
            self.s3.stop()
        return b""


def test_an_outage_during_a_put_commits_nothing_and_the_retry_commits_everything(
        s3, store, bucket, prefix):
    files = {"a.bin": b"first", "b.bin": StopsServer(s3), "c.bin": b"third"}
    try:
        with pytest.raises(Exception) as caught:
            put_mesh(store, files)
        assert not isinstance(caught.value, (InputError, CorruptArtifactError))
    finally:
        if not s3.running:
            s3.start()
    assert not store.exists(mesh_key())
    assert store.keys() == []
    assert not any(name.endswith("manifest.json") for name in objects(bucket, prefix))

    manifest = put_mesh(store, {"a.bin": b"first", "b.bin": b"second", "c.bin": b"third"})
    assert set(manifest.files) == {"a.bin", "b.bin", "c.bin"}
    store.verify(mesh_key())
    assert store.read_bytes(mesh_key(), "b.bin") == b"second"


def test_outage_errors_are_ones_the_service_retries(s3, store):
    from facecap.tasks.runner import is_transient

    put_mesh(store, {"mesh.ply": b"ply data"})
    errors = {}
    s3.stop()
    try:
        for name, call in store_calls(store).items():
            try:
                call()
            except Exception as exc:  # noqa: BLE001 - classified below
                errors[name] = exc
    finally:
        s3.start()
    assert set(errors) == set(store_calls(store))
    not_retried = {name: type(exc).__name__ for name, exc in errors.items()
                   if not is_transient(exc)}
    assert not_retried == {}


def test_a_second_writer_that_dies_cannot_damage_a_committed_artifact(store, bucket, prefix):
    uploading = threading.Event()
    released = threading.Event()
    failures: list[BaseException] = []

    class Waits:
        """Writer B's first file: read only after writer A has committed."""

        def read(self, size: int = -1) -> bytes:
            uploading.set()
            released.wait(timeout=30)
            self.read = lambda size=-1: b""
            return b"B" * 64

    class Dies:
        def read(self, size: int = -1) -> bytes:
            raise RuntimeError("writer B killed")

    def writer_b():
        try:
            put_mesh(open_store(store.url), {"mesh.ply": Waits(), "texture.png": Dies()})
        except BaseException as exc:  # noqa: BLE001 - expected: B dies
            failures.append(exc)

    thread = threading.Thread(target=writer_b)
    thread.start()
    try:
        # B has passed its "already stored?" check and is uploading when A commits.
        assert uploading.wait(timeout=30)
        put_mesh(store, {"mesh.ply": b"A" * 64, "texture.png": b"A"})
    finally:
        released.set()
        thread.join(timeout=60)
    assert len(failures) == 1 and "writer B killed" in str(failures[0])
    store.verify(mesh_key())
    assert store.read_bytes(mesh_key(), "mesh.ply") == b"A" * 64
    # B cleaned up after itself: only A's manifest and A's files are left.
    writer = store.manifest(mesh_key()).folder
    assert set(objects(bucket, prefix)) == {
        f"artifacts/{mesh_key()}/manifest.json", f"artifacts/{mesh_key()}/{writer}/mesh.ply",
        f"artifacts/{mesh_key()}/{writer}/texture.png"}


def test_of_two_writers_that_both_finish_the_first_manifest_wins(store, bucket, prefix):
    """Two hosts compute the same artifact at once (locks are per machine): the second
    commit is refused by S3's create-only write; that writer removes its own files and
    returns the winner's manifest, so both see one artifact."""
    uploaded = threading.Event()
    released = threading.Event()
    results: list = []

    class WaitsAfterUpload:
        """Writer B's only file: uploaded, then B stalls until A has committed."""

        def __init__(self):
            self.done = False

        def read(self, size: int = -1) -> bytes:
            if self.done:
                uploaded.set()
                released.wait(timeout=30)
                return b""
            self.done = True
            return b"B" * 64

    thread = threading.Thread(target=lambda: results.append(
        put_mesh(open_store(store.url), {"mesh.ply": WaitsAfterUpload()})))
    thread.start()
    try:
        assert uploaded.wait(timeout=30)
        winner = put_mesh(store, {"mesh.ply": b"A" * 64})
    finally:
        released.set()
        thread.join(timeout=60)
    assert results == [winner]  # B returns A's manifest, not its own
    assert store.read_bytes(mesh_key(), "mesh.ply") == b"A" * 64
    store.verify(mesh_key())
    assert set(objects(bucket, prefix)) == {f"artifacts/{mesh_key()}/manifest.json",
                                            f"artifacts/{mesh_key()}/{winner.folder}/mesh.ply"}


# --------------------------------------------------------------------------- worker setup


def compose_worker_environment() -> dict[str, str]:
    raw = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    return {k: str(v) for k, v in raw["services"]["worker"]["environment"].items()}


WORKER_SCRIPT = """
import sys
from facecap.tasks.runner import default_store_url
from facecap.tasks.store import artifact_key, open_store
store = open_store(default_store_url())
key = artifact_key("mesh", {}, None, sys.argv[1])
store.put(key, {"mesh.ply": b"from a worker"}, stage="mesh", inputs={}, config=None,
          version=sys.argv[1])
print(store.url, key)
"""


@pytest.mark.parametrize("endpoint_variable", ["compose", "FSSPEC_S3_ENDPOINT_URL"])
def test_a_worker_configured_like_the_compose_workers_uses_the_store(
        s3, prefix, tmp_path, endpoint_variable):
    """A fresh process with only the worker's variables from docker-compose.yml (MinIO's
    address replaced by the test server's) writes to the bucket; the variable fsspec reads,
    named in tasks/store/remote.py, works as well."""
    compose_env = compose_worker_environment()
    endpoints = [name for name, value in compose_env.items() if value == "http://minio:9000"]
    assert endpoints == ["AWS_ENDPOINT_URL_S3"]
    store_url = compose_env["FACECAP_STORE"]
    assert re.fullmatch(r"s3://\$\{FACECAP_S3_BUCKET:-\w+\}/artifacts", store_url)
    env = {
        "PATH": os.environ["PATH"],
        "HOME": str(tmp_path),
        "PYTHONPATH": str(ROOT),
        "FACECAP_HOME": str(tmp_path / "facecap-home"),
        "FACECAP_STORE": f"s3://{BUCKET}/{prefix}",
        **CREDENTIALS,  # compose takes them from .env
        "AWS_RETRY_MODE": compose_env["AWS_RETRY_MODE"],
        "AWS_MAX_ATTEMPTS": compose_env["AWS_MAX_ATTEMPTS"],
    }
    if endpoint_variable == "compose":
        env[endpoints[0]] = s3.url
    else:
        env[endpoint_variable] = s3.url
    version = uuid.uuid4().hex[:8]
    result = subprocess.run([sys.executable, "-c", WORKER_SCRIPT, version], env=env,
                            cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-3000:]
    url, key = result.stdout.split()
    assert url == f"s3://{BUCKET}/{prefix}"
    assert open_store(url).read_bytes(key, "mesh.ply") == b"from a worker"
