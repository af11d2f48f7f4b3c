"""Assets from the package registry: the default face template and a sample real head scan.

Both come from the source distribution of ``menpo3d==0.8.6`` (BSD-3-Clause, Imperial
College London), fetched from the package indexes pip is configured to use (the file alone:
nothing in it is run), checked against a pinned sha256 and unpacked under ``$FACECAP_HOME/assets`` (default
``~/.cache/facecap/assets``). Nothing else is ever downloaded.

* ``template.ply`` + ``template.ljson``: a 53,349-vertex face-and-ears template in the Basel
  Face Model topology, in micrometres, with 68 landmarks (converted to mm on load).
* ``james.obj`` / ``james.jpg`` / ``james.ljson``: a real textured head scan in mm with 68 3D
  landmarks.

A sdist that is already downloaded can be placed in ``$FACECAP_HOME/downloads`` to work
offline; it is verified the same way.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import ssl
import subprocess
import sys
import tarfile
import tempfile
import urllib.request
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import urldefrag, urljoin

from facecap_core.errors import FacecapError
from facecap_core.settings import settings

MENPO3D_SDIST = "menpo3d-0.8.6.tar.gz"
MENPO3D_SHA256 = "96ad2c8b55b74e026cdc190cf6b1564ad7c8e6c53976cf897d6a1bf4940f084a"
MENPO3D_FILES = (
    "template.ply", "template.ljson", "james.obj", "james.obj.mtl", "james.jpg", "james.ljson",
)
MENPO3D_FILE_SHA256 = {
    "template.ply": "2c9898e9582ac2fd76131e5757f063315cbe8781ffbd036e2bb5f1bd1fa8215e",
    "template.ljson": "15d5af3e496d10a71306d9a5d41b3ef0bbf1d603a2aee0fc723a17c9284395fd",
    "james.obj": "80cb729b6a751b25794d9d571668ff3c022f111119b307dd93dc8fbed6eed110",
    "james.obj.mtl": "90aa99e8d939fa6e9849e15c7b39a3364b8814a494a7fe59baca0484104c9ca4",
    "james.jpg": "829589c076a9cb7b8904b08cc0b301a01e75d6096bf2ca01ed7a8e9d4a615a77",
    "james.ljson": "02a9e32271c47db90ec51ec0027eb302b68e52f974d6b2856a3f7e55b13b0ee2",
}
"""sha256 of each unpacked file: a cached copy damaged later (disk fault, an edit) is
refused instead of silently changing every reconstruction."""


def facecap_home() -> Path:
    """The user cache folder: ``$FACECAP_HOME`` or ``~/.cache/facecap``."""
    return settings().home


MENPO3D_PROJECT = "menpo3d"
PYPI_SIMPLE = "https://pypi.org/simple"
DOWNLOAD_TIMEOUT_S = 60
MAX_SDIST_BYTES = 64 * 2**20
"""The sdist is 3.8 MB: an index that sends more than this is not sending it."""


def _download_sdist(dest: Path) -> Path:
    """The menpo3d sdist, verified: a copy placed in ``$FACECAP_HOME/downloads``, else the
    file itself from pip's configured package indexes (PEP 503 simple pages), checked
    against the pinned sha256 as it arrives. Nothing in it is run: ``pip download`` would
    prepare the sdist's metadata first, which runs its ``setup.py`` before any check."""
    cached = facecap_home() / "downloads" / MENPO3D_SDIST
    if cached.is_file():
        return cached
    settings = _pip_settings()
    indexes = [settings["index-url"] or PYPI_SIMPLE, *(settings["extra-index-url"] or "").split()]
    sdist, tried = dest / MENPO3D_SDIST, []
    for index in indexes:
        try:
            links = _sdist_links(index, settings["cert"])
            tried += [] if links else [f"{index}: no {MENPO3D_SDIST}"]
            for url in links:
                if _fetch_verified(url, sdist, settings["cert"]):
                    return sdist
                tried.append(f"{url}: sha256 differs")
        except (OSError, ValueError) as exc:  # unreachable, no such project, a bad page
            tried.append(f"{index}: {' '.join(str(exc).split())[:120]}")
    raise FacecapError(
        f"could not fetch {MENPO3D_SDIST} from the package indexes ({'; '.join(tried)}); "
        f"check pip's index settings, or put {MENPO3D_SDIST} into {cached.parent}")


def _pip_settings() -> dict[str, str | None]:
    """pip's ``index-url``, ``extra-index-url`` and ``cert``, as pip would read them: its
    environment variables first, then its configuration files."""
    settings = {name: os.environ.get(f"PIP_{name.upper().replace('-', '_')}")
                for name in ("index-url", "extra-index-url", "cert")}
    if not all(settings.values()):
        proc = subprocess.run([sys.executable, "-m", "pip", "config", "list"],
                              capture_output=True, text=True)
        for line in proc.stdout.splitlines():
            name, _, value = line.partition("=")
            option = name.rpartition(".")[2]
            if option in settings and not settings[option]:
                settings[option] = value.strip().strip("'\"")
    return settings


def _sdist_links(index: str, cert: str | None) -> list[str]:
    """The URLs of the sdist on an index's page of the project (its links to any other file
    are ignored)."""

    page = f"{index.rstrip('/')}/{MENPO3D_PROJECT}/"
    with _open_url(page, cert) as response:
        text = response.read(4 * 2**20).decode("utf-8", "replace")
    links: list[str] = []

    class Anchors(HTMLParser):
        def handle_starttag(self, tag, attrs):
            href = dict(attrs).get("href") if tag == "a" else None
            if href and urldefrag(href)[0].rsplit("/", 1)[-1] == MENPO3D_SDIST:
                links.append(urljoin(page, href))

    Anchors().feed(text)
    return links


def _open_url(url: str, cert: str | None):
    if url.startswith("file:"):  # a local index: a folder per project with its index.html
        path = Path(urllib.request.url2pathname(url.removeprefix("file://")))
        return open(path / "index.html" if path.is_dir() else path, "rb")
    context = ssl.create_default_context(cafile=cert) if cert else None
    request = urllib.request.Request(url, headers={"Accept": "text/html"})
    return urllib.request.urlopen(request, timeout=DOWNLOAD_TIMEOUT_S, context=context)


def _fetch_verified(url: str, target: Path, cert: str | None) -> bool:
    """Download ``url`` to ``target`` hashing it as it arrives; keep it only if its sha256
    is the pinned one (an index serving more than ``MAX_SDIST_BYTES`` is cut off)."""
    digest, size = hashlib.sha256(), 0
    with _open_url(url, cert) as response, open(target, "wb") as out:
        while (chunk := response.read(2**20)) and size <= MAX_SDIST_BYTES:
            digest.update(chunk)
            out.write(chunk)
            size += len(chunk)
    if size > MAX_SDIST_BYTES or digest.hexdigest() != MENPO3D_SHA256:
        target.unlink()
        return False
    return True


def file_digest(path: Path) -> str:
    with open(path, "rb") as source:
        return hashlib.file_digest(source, "sha256").hexdigest()


def menpo3d_data() -> Path:
    """Folder holding the menpo3d data files (fetched and verified on first use)."""
    target = facecap_home() / "assets" / "menpo3d-0.8.6"
    if all((target / name).is_file() for name in MENPO3D_FILES):
        for name in MENPO3D_FILES:  # ~70 ms for the 5 MB
            if file_digest(target / name) != MENPO3D_FILE_SHA256[name]:
                raise FacecapError(
                    f"the asset {target / name} is damaged (its sha256 is not the pinned one); "
                    f"delete {target} and run `facecap assets` to fetch it again")
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
        tmp = Path(tmp)
        sdist = _download_sdist(tmp)
        digest = file_digest(sdist)
        if digest != MENPO3D_SHA256:
            raise FacecapError(
                f"{sdist} has sha256 {digest}, expected {MENPO3D_SHA256}: the package index "
                "served a different file; delete it and check the index")
        unpacked = tmp / "unpacked"
        unpacked.mkdir()
        with tarfile.open(sdist) as tar:
            for name in MENPO3D_FILES + ("LICENSE.txt",):
                member = tar.getmember(
                    f"menpo3d-0.8.6/{'' if name == 'LICENSE.txt' else 'menpo3d/data/'}{name}")
                with tar.extractfile(member) as src, open(unpacked / name, "wb") as dst:
                    shutil.copyfileobj(src, dst)
        # Rename into place last, so a crash never leaves a half-unpacked asset folder.
        try:
            unpacked.rename(target)
        except OSError:
            if not all((target / name).is_file() for name in MENPO3D_FILES):
                raise
    return target


def default_template_files() -> tuple[Path, Path]:
    """(mesh in µm, 68-landmark LJSON) of the default template."""
    d = menpo3d_data()
    return d / "template.ply", d / "template.ljson"


def james_files() -> tuple[Path, Path]:
    """(textured OBJ in mm, 68-landmark LJSON) of the sample real head scan."""
    d = menpo3d_data()
    return d / "james.obj", d / "james.ljson"


ICT_MODEL_ENV = "FACECAP_ICT_MODEL"


def packaged_ict_model() -> Path:
    """The trimmed ICT Face Model that ships in the package (MIT, USC ICT): skin, sockets and
    eyeballs, the first 30 identity modes in float16 (``facecap_core/data/README.md``)."""
    return Path(__file__).resolve().parent / "data" / "ict_face_model_trimmed.npz"


def default_ict_model() -> Path:
    """The ICT Face Model to use when none is given: ``$FACECAP_ICT_MODEL`` (e.g. the full
    100-mode model), else the packaged trimmed one."""
    return settings().ict_model or packaged_ict_model()


PROVENANCE = """\
Assets used by facecap
- menpo3d==0.8.6 sdist from the package index, sha256 {sha}
  (BSD-3-Clause, Copyright (c) 2014 Imperial College London and others):
    template.ply/.ljson  default template, face + ears, Basel Face Model topology, 68 landmarks
    james.obj/.jpg/.ljson  real textured head scan (mm) with 68 3D landmarks
- Face detector, face mesh and iris models (mediapipe==0.10.21, Apache-2.0, inside the
  package): the 68 face landmarks and the irises (docs/provenance.md).
- Ear detector and ear-contour predictor (facecap's own, trained on renders of ICT
  identities: facecap_core/landmarks/models, docs/ears.md).
- ICT Face Model Light (MIT, Copyright (c) 2020 USC Institute for Creative Technologies):
  synthetic identities; a trimmed copy (30 identity modes) ships in facecap_core/data/,
  --ict-model or FACECAP_ICT_MODEL give another (e.g. the full model).
"""
