"""The command line: results as JSON, and one clear line (no traceback) for bad input."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from facecap_core.meshio import save_landmarks
from facecap_core.template import Template


def facecap(*args, cwd=None, env=None):
    """``facecap ARGS`` in a process of its own (in ``env``, default this one's): exit code,
    stdout, stderr."""
    proc = subprocess.run([sys.executable, "-m", "facecap", *map(str, args)],
                          capture_output=True, text=True, cwd=cwd, env=env, timeout=600)
    return proc.returncode, proc.stdout, proc.stderr


@pytest.fixture(scope="module")
def scan(tmp_path_factory, ict_model):
    """An ICT head as the 'scan', its landmarks, and the same head 2 % larger as a 'mesh'."""
    d = tmp_path_factory.mktemp("cli")
    t = Template.from_ict(ict_model)
    t.to_trimesh().export(d / "scan.ply")
    save_landmarks(d / "scan_landmarks.json", t.landmark_points)
    trimesh.Trimesh(t.vertices * 1.02, t.faces, process=False).export(d / "big.ply")
    save_landmarks(d / "big_landmarks.json", t.landmark_points * 1.02)
    return d


def test_evaluate_json(scan):
    code, out, err = facecap("evaluate", scan / "big.ply", "--scan", scan / "scan.ply",
                             "--scan-landmarks", scan / "scan_landmarks.json",
                             "--mesh-landmarks", scan / "big_landmarks.json", "--json")
    assert code == 0, err
    doc = json.loads(out)
    sim, met = doc["similarity"], doc["metric"]
    assert set(sim) >= {"accuracy", "completion", "scale"}
    assert set(sim["accuracy"]) == {"mean", "std", "median", "under_1mm", "under_2mm"}
    assert abs(sim["scale"] - 1 / 1.02) < 1e-3 and sim["accuracy"]["mean"] < 0.05
    assert met["scale"] == 1.0 and met["accuracy"]["mean"] > 0.3  # 2 % too big is seen
    assert set(sim["ears"]) == {"accuracy", "completion"}
    assert sim["ears"]["accuracy"]["mean"] < 0.05 and met["ears"]["accuracy"]["mean"] > 0.3


def test_evaluate_prints_the_face_and_the_ear_table(scan):
    code, out, err = facecap("evaluate", scan / "big.ply", "--scan", scan / "scan.ply",
                             "--scan-landmarks", scan / "scan_landmarks.json",
                             "--mesh-landmarks", scan / "big_landmarks.json")
    assert code == 0, err
    face, ears = out.split("\nEar region\n")
    for table in (face, ears):
        assert "| Method | Captures | Accuracy mean |" in table
        assert "| big.ply (similarity) | 1 |" in table and "| big.ply (metric) | 1 |" in table
    assert "ears: accuracy under 1 mm" in ears


def test_evaluate_one_protocol_prints_one_object(scan, tmp_path):
    code, out, err = facecap("evaluate", scan / "scan.ply", "--scan", scan / "scan.ply",
                             "--scan-landmarks", scan / "scan_landmarks.json",
                             "--protocol", "metric", "--json", "--heatmap", tmp_path / "h.png")
    assert code == 0, err
    assert json.loads(out)["accuracy"]["mean"] < 1e-3
    assert (tmp_path / "h_metric.png").stat().st_size > 1000


def test_a_heat_map_is_never_written_through_a_link_nor_over_an_input(scan, tmp_path, capfd):
    """A link planted at a derived name (``s_metric.png`` of ``--heatmap s.png``) pointing at
    the scan being scored: the heat map replaces the link, the scan is unchanged. A hard link
    to an input at that name is refused before any scoring."""
    shown = tmp_path / "shown"
    shown.mkdir()
    copy = tmp_path / "scan.ply"
    copy.write_bytes((scan / "scan.ply").read_bytes())
    before = copy.read_bytes()
    (shown / "s_metric.png").symlink_to(copy)
    code, out, err = facecap_here(capfd, "evaluate", copy, "--scan", copy, "--scan-landmarks",
                                  scan / "scan_landmarks.json", "--protocol", "metric",
                                  "--json", "--heatmap", shown / "s.png")
    assert code == 0, err
    assert copy.read_bytes() == before
    assert not (shown / "s_metric.png").is_symlink()
    assert (shown / "s_metric.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    (shown / "s_metric.png").unlink()
    (shown / "s_metric.png").hardlink_to(copy)
    code, out, err = facecap_here(capfd, "evaluate", copy, "--scan", copy, "--scan-landmarks",
                                  scan / "scan_landmarks.json", "--protocol", "metric",
                                  "--heatmap", shown / "s.png")
    assert_one_clear_line(code, out, err, f"would replace the input {copy}")
    assert copy.read_bytes() == before


BAD = {
    "missing mesh": (["evaluate", "{d}/nope.ply", "--scan", "{s}/scan.ply",
                      "--scan-landmarks", "{s}/scan_landmarks.json"], "not found"),
    "non-mesh file": (["evaluate", "{d}/notes.txt", "--scan", "{s}/scan.ply",
                       "--scan-landmarks", "{s}/scan_landmarks.json"], "not a mesh"),
    "garbage ply": (["evaluate", "{d}/garbage.ply", "--scan", "{s}/scan.ply",
                     "--scan-landmarks", "{s}/scan_landmarks.json"], "mesh"),
    "triangles naming absent vertices": (["evaluate", "{d}/far.ply", "--scan", "{s}/scan.ply",
                                          "--scan-landmarks", "{s}/scan_landmarks.json"],
                                         "name vertex 7 of 3"),
    "triangles naming negative vertices": (["evaluate", "{d}/negative.ply", "--scan",
                                            "{s}/scan.ply", "--scan-landmarks",
                                            "{s}/scan_landmarks.json"], "name vertex -2 of 3"),
    "heat map of an unknown image type": (["evaluate", "{s}/scan.ply", "--scan", "{s}/scan.ply",
                                           "--scan-landmarks", "{s}/scan_landmarks.json",
                                           "--heatmap", "{d}/h.jpgx"], ".png"),
    "heat map under a file": (["evaluate", "{s}/scan.ply", "--scan", "{s}/scan.ply",
                               "--scan-landmarks", "{s}/scan_landmarks.json",
                               "--heatmap", "{d}/notes.txt/h.png"], "notes.txt is a file"),
    "a vertex 1e30 mm away": (["evaluate", "{d}/huge.ply", "--scan", "{s}/scan.ply",
                                "--scan-landmarks", "{s}/scan_landmarks.json"],
                               "coordinate of 1e+30, beyond"),
    "a mesh with 2-D vertices": (["evaluate", "{d}/flat.obj", "--scan", "{s}/scan.ply",
                                  "--scan-landmarks", "{s}/scan_landmarks.json"],
                                 "vertices with 2 coordinates, not 3"),
    "a mesh whose every match on the scan is one point": (
        ["evaluate", "{d}/point.obj", "--scan", "{s}/scan.ply", "--scan-landmarks",
         "{s}/scan_landmarks.json"], "cannot be aligned to the scan"),
    "68 identical scan landmarks": (["evaluate", "{s}/scan.ply", "--scan", "{s}/scan.ply",
                                     "--scan-landmarks", "{d}/same.json"], "landmarks"),
    "a mesh whose every triangle is a point": (
        ["evaluate", "{d}/points.ply", "--scan", "{s}/scan.ply", "--scan-landmarks",
         "{s}/scan_landmarks.json"], "mesh file {d}/points.ply has no triangle with an area"),
    "a mesh whose every triangle is a line": (
        ["evaluate", "{d}/lines.ply", "--scan", "{s}/scan.ply", "--scan-landmarks",
         "{s}/scan_landmarks.json"], "mesh file {d}/lines.ply has no triangle with an area"),
    "a scan whose every triangle is a point": (
        ["evaluate", "{s}/scan.ply", "--scan", "{d}/points.ply", "--scan-landmarks",
         "{s}/scan_landmarks.json"], "scan file {d}/points.ply has no triangle with an area"),
    "a mesh without faces": (["evaluate", "{d}/faceless.ply", "--scan", "{s}/scan.ply",
                              "--scan-landmarks", "{s}/scan_landmarks.json"],
                             "holds no triangles"),
    "a scan without faces": (["evaluate", "{s}/scan.ply", "--scan", "{d}/faceless.ply",
                              "--scan-landmarks", "{s}/scan_landmarks.json"],
                             "scan file {d}/faceless.ply holds no triangles"),
    "synth: negative seed": (["synth", "--out", "{d}/o", "--seed", "-1"], "seed"),
    "synth: a frame a year": (["synth", "--out", "{d}/o", "--fps", "0.0001"], "fps"),
    "scan without landmarks": (["evaluate", "{s}/big.ply", "--scan", "{s}/scan.ply"],
                               "landmarks"),
    "landmarks of the wrong size": (["evaluate", "{s}/big.ply", "--scan", "{s}/scan.ply",
                                     "--scan-landmarks", "{d}/five.json"], "5 points"),
    "synth: missing subject mesh": (["synth", "--out", "{d}/o", "--subject", "{d}/head.obj",
                                     "--subject-landmarks", "{s}/scan_landmarks.json"],
                                    "not found"),
    "synth: non-mesh subject": (["synth", "--out", "{d}/o", "--subject", "{d}/notes.txt",
                                 "--subject-landmarks", "{s}/scan_landmarks.json"], "not a mesh"),
    "synth: mesh without landmarks": (["synth", "--out", "{d}/o", "--subject",
                                       "{s}/scan.ply"], "landmarks"),
    "synth: bad value": (["synth", "--out", "{d}/o", "--fps", "-3"], "fps"),
    "synth: missing config": (["synth", "--out", "{d}/o", "--config", "{d}/c.yaml"],
                              "not found"),
    "synth: unknown config key": (["synth", "--out", "{d}/o", "--config", "{d}/typo.yaml"],
                                  "colour"),
}


def write_bad_inputs(tmp_path: Path, scan: Path) -> None:
    """The files the BAD cases name under ``{d}``."""
    (tmp_path / "notes.txt").write_text("not a mesh")
    (tmp_path / "garbage.ply").write_bytes(b"ply\nformat nonsense\n\x00\xff" * 10)
    (tmp_path / "five.json").write_text(json.dumps(np.zeros((5, 3)).tolist()))
    (tmp_path / "typo.yaml").write_text("colour: red\n")
    (tmp_path / "same.json").write_text(json.dumps([[1.0, 2.0, 3.0]] * 68))
    (tmp_path / "flat.obj").write_text("v 0 0\nv 1 0\nv 0 1\nf 1 2 3\n")
    # Four vertices 3 mm out from the scan's nose tip, 1 µm apart: each one's closest scan
    # point is the tip itself.
    head = trimesh.load(scan / "scan.ply", process=False)
    nose = json.loads((scan / "scan_landmarks.json").read_text())["landmarks"][30]
    tip = int(np.argmin(np.linalg.norm(head.vertices - nose, axis=1)))
    normal = head.vertex_normals[tip]
    side = np.cross(normal, [0.0, 0.0, 1.0])
    side /= np.linalg.norm(side)
    up = np.cross(normal, side)
    corners = [head.vertices[tip] + 3 * normal + 1e-3 * (a * side + b * up)
               for a, b in ((0, 0), (1, 0), (0, 1), (1, 1))]
    (tmp_path / "point.obj").write_text("".join(f"v {x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in corners)
                                        + "f 1 2 3\nf 2 4 3\n")
    (tmp_path / "huge.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
        "end_header\n0 0 0\n1e30 0 0\n0 1 0\n3 0 1 2\n")
    for name, index in (("far.ply", 7), ("negative.ply", -2)):
        (tmp_path / name).write_text(
            "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
            "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
            f"end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 {index}\n")
    # The scan's vertices, every triangle collapsed to one of them (i, i, i) or to a line
    # (i, i, j): perfect "accuracy", no surface; and the scan's vertices with no faces.
    head = trimesh.load(scan / "scan.ply", process=False)
    header = ("ply\nformat ascii 1.0\nelement vertex {n}\nproperty float x\nproperty float y\n"
              "property float z\nelement face {f}\nproperty list uchar int vertex_indices\n"
              "end_header\n")
    rows = "".join(f"{x} {y} {z}\n" for x, y, z in head.vertices)
    n = len(head.vertices)
    for name, corners in (("points.ply", lambda i: (i, i, i)),
                          ("lines.ply", lambda i: (i, i, (i + 1) % n))):
        (tmp_path / name).write_text(header.format(n=n, f=n) + rows + "".join(
            "3 {} {} {}\n".format(*corners(i)) for i in range(n)))
    (tmp_path / "faceless.ply").write_text(header.format(n=n, f=0) + rows)


def facecap_here(capfd, *args):
    """``facecap`` run in this process, as its console script runs it (exit code, stdout,
    stderr), without a process start for each case. A Python warning would reach a user's
    terminal as another line; here pytest would catch it first, so none may be raised."""
    import warnings

    from facecap.cli import main

    capfd.readouterr()
    with warnings.catch_warnings(record=True) as raised:
        warnings.simplefilter("always")
        code = main([str(a) for a in args])
    out, err = capfd.readouterr()
    assert [str(w.message) for w in raised] == [], err
    return code, out, err


def assert_one_clear_line(code: int, out: str, err: str, expected: str) -> None:
    assert code == 2, (out, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("facecap: error: "), err
    assert expected in lines[0] and "Traceback" not in err


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_input_is_one_clear_line(case, scan, tmp_path, capfd):
    write_bad_inputs(tmp_path, scan)
    args, expected = BAD[case]
    code, out, err = facecap_here(capfd, *[a.format(d=tmp_path, s=scan) for a in args])
    assert_one_clear_line(code, out, err, expected.format(d=tmp_path, s=scan))


@pytest.mark.parametrize("case", ["missing mesh", "synth: unknown config key"])
def test_the_command_in_its_own_process_says_bad_input_in_one_line(case, scan, tmp_path):
    """The same as a user's shell sees it: a fresh process, whose imports may print too."""
    write_bad_inputs(tmp_path, scan)
    args, expected = BAD[case]
    code, out, err = facecap(*[a.format(d=tmp_path, s=scan) for a in args])
    assert_one_clear_line(code, out, err, expected.format(d=tmp_path, s=scan))


def test_an_unexpected_exception_is_reported_as_a_bug_with_its_log(tmp_path, monkeypatch,
                                                                   capsys):
    """A failure nobody anticipated is not blamed on the input: one line says it is a bug
    and names the log file that holds its traceback; the exit code is not bad input's 2."""
    from facecap import cli
    from facecap_core import evaluation

    def broken(*args, **kwargs):
        raise ZeroDivisionError("float division by zero")

    monkeypatch.setenv("FACECAP_HOME", str(tmp_path / "home"))
    monkeypatch.setattr(evaluation, "evaluate", broken)
    mesh = tmp_path / "m.ply"
    mesh.write_text("ply")
    code = cli.main(["evaluate", str(mesh), "--scan", str(mesh)])
    err = capsys.readouterr().err.strip()
    assert code == 1 and "\n" not in err
    assert err.startswith("facecap: internal error (a bug in facecap") and "ZeroDivisionError" in err
    log = next((tmp_path / "home" / "logs").glob("crash-*.log"))
    assert str(log) in err
    text = log.read_text()
    assert "Traceback" in text and "in broken" in text and "evaluate" in text.splitlines()[0]


# --------------------------------------------------------------------------- usage errors


USAGE_ERRORS = {
    # argv: (argparse's message, the help to see)
    "an unknown option": (["forget", "-x"], "the following arguments are required: subject",
                          "facecap forget"),
    "an unknown option after the arguments": (["forget", "bob", "-x"],
                                              "unrecognized arguments: -x", "facecap forget"),
    "not a number": (["store", "prune", "--older-than-days", "abc"],
                     "argument --older-than-days: invalid float value: 'abc'",
                     "facecap store prune"),
    "an unknown command": (["reconstruc"], "argument command: invalid choice: 'reconstruc'",
                           "facecap"),
    "a missing required option": (["reconstruct", "v.mp4"],
                                  "the following arguments are required: --out",
                                  "facecap reconstruct"),
    "no command": ([], "the following arguments are required: command", "facecap"),
    "store without its command": (["store"], "the following arguments are required: "
                                  "store_command", "facecap store"),
    "a port past 65535": (["pages", "--port", "70000"], "argument --port: 70000 is not a "
                          "port number; give a whole number from 0 to 65535", "facecap pages"),
    "a negative port": (["pages", "--port", "-1"], "argument --port: -1 is not a port number",
                        "facecap pages"),
    "a pages port past 65535": (["serve", "--root", "r", "--out", "o", "--pages-port", "70000"],
                                "argument --pages-port: 70000 is not a port number",
                                "facecap serve"),
}


@pytest.mark.parametrize("case", sorted(USAGE_ERRORS))
def test_a_usage_error_is_one_line_naming_the_commands_help(case, capfd):
    """argparse's own message, no usage lines: ``facecap: error: <message>; see 'facecap
    <command> --help'``, exit code 2."""
    from facecap.cli import main

    argv, message, command = USAGE_ERRORS[case]
    code = main(argv)
    out, err = capfd.readouterr()
    assert code == 2 and out == "", err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"facecap: error: {message}"), err
    assert lines[0].endswith(f"; see '{command} --help'"), err


def test_help_still_prints_the_help(capfd):
    from facecap.cli import main

    for argv in (["--help"], ["store", "prune", "--help"]):
        with pytest.raises(SystemExit) as exit_:
            main(argv)
        out, err = capfd.readouterr()
        assert exit_.value.code == 0 and out.startswith("usage: facecap") and err == ""


# --------------------------------------------------------------------------- the store


@pytest.fixture(scope="module")
def orbit(tmp_path_factory) -> Path:
    """A 40-frame video that passes the preflight (it shows no face: no stage may run)."""
    from tests.media import write_video
    from tests.test_bad_inputs import orbit_frames

    return write_video(tmp_path_factory.mktemp("orbit") / "take.mp4", orbit_frames(40))


def test_a_store_in_memory_is_refused_by_every_command(orbit, tmp_path, monkeypatch, capfd):
    """``memory://`` lives as long as the process: a run's artifacts would vanish at exit.
    Refused in one line by each command that opens the store, given as ``--store`` or as
    FACECAP_STORE; no result is written."""
    from facecap.cli import main

    root, out = tmp_path / "dataset", tmp_path / "out"
    (root / "anna").mkdir(parents=True)
    (root / "anna" / "take.mp4").write_bytes(orbit.read_bytes())
    commands = [["reconstruct", orbit, "--out", out], ["dataset", root, "--out", out],
                ["evaluate-dataset", root, "--out", out], ["forget", "anna", "--out", out],
                ["store", "prune", "--older-than-days", "1"]]
    for argv in commands:
        for flag in (["--store", "memory://x"], []):
            monkeypatch.setenv("FACECAP_STORE", "" if flag else "memory://y")
            code = main([str(a) for a in argv + flag])
            err = capfd.readouterr().err
            lines = err.strip().splitlines()
            assert code == 2 and len(lines) == 1, (argv, err)
            assert lines[0] == (f"facecap: error: the store memory://{'x' if flag else 'y'} "
                                "is held in this process's memory, so its artifacts would "
                                "vanish when facecap exits; give a folder or an "
                                "s3://bucket/prefix URL (--store or FACECAP_STORE)"), argv
    assert not out.exists() or not any(out.iterdir())  # the dataset command made it, empty


# --------------------------------------------------------------------------- bugs


def evaluate_a_mesh(tmp_path: Path) -> int:
    """``facecap evaluate`` of a mesh file in ``tmp_path`` against itself, in this process
    (the tests make its evaluation fail as they need); returns the exit code."""
    from facecap import cli

    mesh = tmp_path / "m.ply"
    mesh.write_bytes(b"ply")
    return cli.main(["evaluate", str(mesh), "--scan", str(mesh)])


def test_a_bug_on_a_full_disk_is_still_one_line(tmp_path, monkeypatch, capsys):
    """The crash log cannot be written (no space left): the line still says it is a bug,
    what was raised, and that the traceback could not be saved, and why."""
    import errno
    import os

    from facecap_core import evaluation

    def broken(*args, **kwargs):
        raise ZeroDivisionError("float division by zero")

    def full(fd, data):
        os.write(fd, b"the first bytes")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    from facecap.tasks import own_files

    monkeypatch.setenv("FACECAP_HOME", str(tmp_path / "home"))
    monkeypatch.setattr(evaluation, "evaluate", broken)
    monkeypatch.setattr(own_files, "_write_all", full)
    code = evaluate_a_mesh(tmp_path)
    err = capsys.readouterr().err
    assert code == 1 and len(err.strip().splitlines()) == 1, err
    assert err.startswith("facecap: internal error (a bug in facecap, not a problem with your "
                          "input): ZeroDivisionError: float division by zero; "), err
    assert "the traceback could not be saved (No space left on device)" in err
    assert not list((tmp_path / "home" / "logs").glob("crash-*.log"))  # no empty log left


def test_an_error_on_a_full_prefect_disk_is_the_disk(tmp_path, monkeypatch, capsys):
    """Prefect's server answers a write to its full database with "500 Internal Server
    Error": with the disk of PREFECT_HOME full, that is one line naming the folder and what
    to do, exit 2; the same error with space left stays a bug (exit 1)."""
    import os

    from facecap_core import evaluation

    def server_error(*args, **kwargs):
        raise RuntimeError("Server error '500 Internal Server Error' for url .../set_state")

    real_statvfs = os.statvfs
    prefect_home = tmp_path / "prefect"
    prefect_home.mkdir()

    def full_prefect_disk(path):
        stats = real_statvfs(path)
        if Path(path) != prefect_home:
            return stats
        return os.statvfs_result((stats.f_bsize, stats.f_frsize, stats.f_blocks, 0, 0,
                                  *stats[5:]))

    monkeypatch.setenv("FACECAP_HOME", str(tmp_path / "home"))
    monkeypatch.setenv("PREFECT_HOME", str(prefect_home))
    monkeypatch.setattr(evaluation, "evaluate", server_error)
    code = evaluate_a_mesh(tmp_path)
    assert code == 1 and "internal error" in capsys.readouterr().err  # space left: a bug
    monkeypatch.setattr(os, "statvfs", full_prefect_disk)
    code = evaluate_a_mesh(tmp_path)
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert err.startswith(f"facecap: error: no space left on the disk of PREFECT_HOME "
                          f"{prefect_home} (RuntimeError: Server error '500"), err
    assert "free space there and run again" in err


# --------------------------------------------------------------------------- FACECAP_HOME


@pytest.mark.parametrize("home", ["/dev/null", "file", "file/sub"])
def test_a_facecap_home_that_is_not_a_folder_is_one_line(home, orbit, tmp_path, monkeypatch,
                                                         capfd):
    """Before anything: not the traceback of the first folder made under it (the assets,
    the crash log)."""
    from facecap.cli import main

    (tmp_path / "file").write_text("a file")
    value = home if home.startswith("/") else str(tmp_path / home)
    monkeypatch.setenv("FACECAP_HOME", value)
    _refused_in_one_line(main, capfd, "FACECAP_HOME", value, "the default (~/.cache/facecap)",
                         [["assets"], ["reconstruct", str(orbit), "--out", str(tmp_path / "out")]])
    assert not (tmp_path / "out").exists()


def _refused_in_one_line(main, capfd, variable: str, value: str, default: str, argvs) -> None:
    """Each command line of ``argvs`` ends with one line naming ``variable``'s bad value and
    what to do, exit 2."""
    for argv in argvs:
        code = main(argv)
        err = capfd.readouterr().err
        lines = err.strip().splitlines()
        assert code == 2 and len(lines) == 1, err
        assert lines[0].startswith(f"facecap: error: invalid {variable}={value!r} in the "
                                   "environment: "), err
        assert "not a folder" in lines[0], err
        assert lines[0].endswith(f"; set {variable} to a writable folder, or unset it for "
                                 f"{default}"), err


@pytest.mark.parametrize("home", ["/dev/null", "file", "file/sub"])
def test_a_prefect_home_that_is_not_a_folder_is_one_line(home, orbit, tmp_path, monkeypatch,
                                                         capfd):
    """PREFECT_HOME is the user's as much as FACECAP_HOME: refused in one line naming it,
    exit 2, before Prefect is asked (it warned, then its server did not start: exit 1)."""
    from facecap.cli import main

    (tmp_path / "file").write_text("a file")
    value = home if home.startswith("/") else str(tmp_path / home)
    monkeypatch.setenv("FACECAP_HOME", str(tmp_path / "facecap-home"))
    monkeypatch.setenv("PREFECT_HOME", value)
    _refused_in_one_line(main, capfd, "PREFECT_HOME", value, "Prefect's default (~/.prefect)",
                         [["forget", "anna", "--out", str(tmp_path / "out")],
                          ["reconstruct", str(orbit), "--out", str(tmp_path / "out")]])
    assert not (tmp_path / "out").exists()
