"""Biometric data has a lifecycle: a subject forgotten, old artifacts pruned; nothing of
another subject is touched."""

from __future__ import annotations

import json
import time
from datetime import UTC, datetime
from pathlib import Path

import pytest

from facecap.cli import main
from facecap.pages.stored import store_page
from facecap.tasks.graph import stage_key
from facecap.tasks.lifecycle import derived, forget, prune, prune_unreferenced
from facecap.tasks.outputs import RECORD_NAME, write_results
from facecap.tasks.runner import ingest
from facecap.tasks.store import open_store
from facecap_core.errors import InputError


def chain(store_url: str, video: Path) -> dict[str, str]:
    """A capture's input artifact and two stage artifacts made from it, one from the other."""
    store = open_store(store_url)
    keys = {"video": ingest(store_url, video, "video.mp4")}
    for stage, made_from in (("keyframes", {"video": keys["video"]}),
                             ("poses", {"video": keys["video"], "keyframes": None})):
        made_from = {k: v or keys["keyframes"] for k, v in made_from.items()}
        keys[stage] = stage_key(stage, made_from, {})
        store.put(keys[stage], {"out.json": stage.encode()}, stage=stage, inputs=made_from,
                  config={}, version="1")
    return keys


@pytest.fixture
def world(tmp_path):
    """Two subjects in a dataset folder, their artifacts, results and evaluation history."""
    root, out, store_url = tmp_path / "data", tmp_path / "out", str(tmp_path / "store")
    keys = {}
    for subject in ("alice", "bob"):
        (root / subject).mkdir(parents=True)
        video = root / subject / "take1.mp4"
        video.write_bytes(f"the face of {subject}".encode())
        (root / subject / "scan.ply").write_bytes(f"the scan of {subject}".encode())
        keys[subject] = chain(store_url, video)
        (out / subject / "take1").mkdir(parents=True)
        report = {"store": store_url,
                  "stages": {s: {"key": keys[subject][s]} for s in ("keyframes", "poses")}}
        # The run's page, kept in the store for the UI's link, and named by the report.
        keys[subject]["page"] = store_page(open_store(store_url), report,
                                           f"the page of {subject}".encode())
        # Written as a run writes it: through the results writer, which records it.
        write_results(out / subject / "take1", {"report.json": json.dumps(
            {**report, "page": {"key": keys[subject]["page"]}}).encode()})
    (out / "evaluations").mkdir()
    (out / "evaluations" / "20261101T020000000000Z.json").write_text(json.dumps(
        {"captures": {"alice/take1": {}, "bob/take1": {}},
         "carried": {"alice/take2": {}, "bob/take2": {}},
         "regressions": [{"capture": "alice/take1"}]}))
    return {"root": root, "out": out, "store": store_url, "keys": keys}


def test_derived_follows_the_inputs_down(world):
    store = open_store(world["store"])
    alice = world["keys"]["alice"]
    assert derived(store, {alice["video"]}) == set(alice.values())
    assert derived(store, {alice["poses"]}) == {alice["poses"], alice["page"]}


def test_forget_removes_the_subject_and_nothing_else(world):
    store = open_store(world["store"])
    before = set(store.keys())
    dry = forget(store, "alice", world["root"], world["out"], dry_run=True)
    assert set(store.keys()) == before and (world["out"] / "alice").is_dir()
    removal = forget(store, "alice", world["root"], world["out"])
    assert removal.artifacts == dry.artifacts == sorted(world["keys"]["alice"].values())
    assert set(store.keys()) == set(world["keys"]["bob"].values())
    assert not (world["out"] / "alice").exists() and (world["out"] / "bob").is_dir()
    history = json.loads((world["out"] / "evaluations" / "20261101T020000000000Z.json")
                         .read_text())
    assert history == {"captures": {"bob/take1": {}}, "carried": {"bob/take2": {}},
                       "regressions": []}
    assert removal.history_entries == 1


def test_forget_during_a_run_of_the_subject_says_what_it_kept(world, capfd):
    """A run of the subject in progress holds leases on what it reads and makes: forget
    removes everything else, keeps those, and ends in one line that says so and what to do,
    exit 2 (not 0: the subject's data is still there); once the run has ended, forget again
    removes the rest."""
    from facecap.tasks.runner import lease, run_leases
    from tests.test_bad_inputs import assert_one_line_error, facecap

    store = open_store(world["store"])
    alice = world["keys"]["alice"]
    with run_leases():
        lease(store, alice["video"])
        lease(store, alice["keyframes"])
        code, out, err = facecap(capfd, "forget", "alice", "--root", world["root"],
                                 "--store", world["store"])
        assert_one_line_error(code, err, [
            "a run in progress uses 2 artifacts of alice",
            f"run facecap forget alice --root {world['root']} --store {world['store']} again "
            "when that run has ended"])
        assert "a run in progress" not in out  # said once: the error line
        assert set(store.keys()) == {alice["video"], alice["keyframes"],
                                     *world["keys"]["bob"].values()}
    code, _, err = facecap(capfd, "forget", "alice", "--root", world["root"], "--store",
                           world["store"])
    assert code == 0, err
    assert set(store.keys()) == set(world["keys"]["bob"].values())


def test_forget_refuses_names_that_are_not_subjects(world, tmp_path):
    store = open_store(world["store"])
    for name in ("", "..", "alice/take1", "../out"):
        with pytest.raises(InputError, match="not a subject name"):
            forget(store, name, world["root"], world["out"])
    with pytest.raises(InputError, match="nothing of subject 'carol'"):
        forget(store, "carol", world["root"], world["out"])
    with pytest.raises(InputError, match="is a summary"):
        forget(store, "evaluations", world["root"], world["out"])
    before = set(store.keys())
    # Links to a folder outside OUT, to another subject's results, to OUT itself.
    for target in (tmp_path / "data" / "bob", world["out"] / "bob", world["out"]):
        (world["out"] / "mallory").unlink(missing_ok=True)
        (world["out"] / "mallory").symlink_to(target)
        with pytest.raises(InputError, match="is a link"):
            forget(store, "mallory", None, world["out"])
    assert set(store.keys()) == before and (world["out"] / "evaluations").is_dir()
    assert (tmp_path / "data" / "bob" / "take1.mp4").is_file()
    assert (world["out"] / "bob" / "take1" / "report.json").is_file()


def test_forget_with_the_results_alone_removes_the_inputs_they_were_made_from(world):
    """Without the dataset folder, the reports lead to the stage artifacts and up to the
    video they were made from; the mesh the nightly evaluation stored goes too."""
    store = open_store(world["store"])
    mesh = world["out"] / "alice" / "take1" / "mesh.ply"
    write_results(mesh.parent, {"mesh.ply": b"alice's fitted mesh"})
    copy = ingest(world["store"], mesh, "mesh.ply")
    (world["out"] / "dataset.json").write_text(json.dumps(
        {"captures": 2, "done": ["alice/take1", "bob/take1"], "failed": {},
         "consistency": [{"subject": "alice", "capture_a": "take1"}]}))
    removal = forget(store, "alice", None, world["out"])
    assert set(removal.artifacts) == {*world["keys"]["alice"].values(), copy}
    assert set(store.keys()) == set(world["keys"]["bob"].values())
    summary = json.loads((world["out"] / "dataset.json").read_text())
    assert summary["done"] == ["bob/take1"] and summary["consistency"] == []


def test_forget_after_the_store_was_emptied_still_removes_the_results(world):
    """The reports name artifacts already pruned from the store they name: the results
    folder (which holds the face) still goes. A file where a results folder would be is
    refused before anything is removed."""
    store = open_store(world["store"])
    for key in list(store.keys()):
        store.delete(key)
    (world["out"] / "carol").write_text("not a folder")
    with pytest.raises(InputError, match="is a file"):
        forget(store, "carol", None, world["out"])
    removal = forget(store, "alice", None, world["out"])
    assert removal.artifacts == [] and not (world["out"] / "alice").exists()
    assert removal.captures == ["alice/take1"]


def test_forget_refuses_a_store_that_holds_none_of_the_reported_artifacts(world, tmp_path):
    other = open_store(str(tmp_path / "other-store"))
    ingest(other.url, world["root"] / "bob" / "take1.mp4", "video.mp4")
    with pytest.raises(InputError, match="give that store"):
        forget(other, "alice", None, world["out"])
    assert (world["out"] / "alice").is_dir()
    assert set(open_store(world["store"]).keys()) >= set(world["keys"]["alice"].values())


def test_prune_removes_what_is_older_and_what_was_made_from_it(world, tmp_path):
    store = open_store(world["store"])
    time.sleep(0.01)
    cut = datetime.fromisoformat(store.manifest(world["keys"]["bob"]["poses"]).created)
    time.sleep(0.01)
    video = tmp_path / "new.mp4"
    video.write_bytes(b"a later capture")
    late = chain(world["store"], video)
    # Committed before the cut: all of alice's and bob's video and keyframes; bob's poses,
    # committed at the cut, go too, being made from his keyframes. The later capture stays.
    removal = prune(store, cut)
    assert set(store.keys()) == set(late.values())
    assert set(removal.artifacts) == {*world["keys"]["alice"].values(),
                                      *world["keys"]["bob"].values()}


def test_prune_unreferenced_keeps_what_a_result_names_and_what_it_was_made_from(world,
                                                                              tmp_path):
    store = open_store(world["store"])
    video = tmp_path / "abandoned.mp4"
    video.write_bytes(b"a capture whose run never wrote a report")
    orphan = chain(world["store"], video)
    time.sleep(0.01)
    now = datetime.now(UTC)
    alice, bob = world["keys"]["alice"], world["keys"]["bob"]
    # Reports name keyframes and poses; the video they were made from is kept with them.
    removal = prune_unreferenced(store, [world["out"]], now, dry_run=True)
    assert set(removal.artifacts) == set(orphan.values())
    # Younger than the cut: a run still in progress, spared.
    cut = datetime.fromisoformat(store.manifest(orphan["video"]).created)
    assert prune_unreferenced(store, [world["out"]], cut).artifacts == []
    # Only alice's results keep artifacts: bob's go with the orphan.
    removal = prune_unreferenced(store, [world["out"] / "alice"], now)
    assert set(removal.artifacts) == {*orphan.values(), *bob.values()}
    assert set(store.keys()) == set(alice.values())
    with pytest.raises(InputError, match="results folder not found"):
        prune_unreferenced(store, [tmp_path / "nowhere"], now)


def test_the_commands_say_what_they_removed(world, capsys, tmp_path):
    code = main(["forget", "bob", "--root", str(world["root"]), "--out", str(world["out"]),
                 "--store", world["store"]])
    assert code == 0
    assert "removed 4 artifacts, 1 results folders" in capsys.readouterr().out
    code = main(["store", "prune", "--older-than-days", "0", "--store", world["store"],
                 "--dry-run"])
    assert code == 0 and "would remove 4 artifacts" in capsys.readouterr().out
    for days in ("-1", "800000"):
        assert main(["store", "prune", "--older-than-days", days, "--store",
                     world["store"]]) == 2
        assert "is not an age" in capsys.readouterr().err
    assert main(["store", "prune", "--unreferenced", "--store", world["store"]]) == 2
    assert "give them with --out" in capsys.readouterr().err
    # bob is forgotten; results elsewhere (carol's) name none of alice's artifacts.
    (tmp_path / "elsewhere" / "carol" / "take1").mkdir(parents=True)
    (tmp_path / "elsewhere" / "carol" / "take1" / "report.json").write_text(json.dumps(
        {"stages": {"keyframes": {"key": "keyframes-" + "0" * 32}}}))
    code = main(["store", "prune", "--unreferenced", "--older-than-days", "0", "--out",
                 str(world["out"]), "--out", str(tmp_path / "elsewhere"), "--store",
                 world["store"]])
    assert code == 0 and "removed 0 artifacts" in capsys.readouterr().out
    code = main(["store", "prune", "--unreferenced", "--older-than-days", "0", "--out",
                 str(tmp_path / "elsewhere"), "--store", world["store"]])
    assert code == 0 and "removed 4 artifacts" in capsys.readouterr().out


@pytest.mark.parametrize("created", ["2026-01-01T02:00:00", "last week"],
                         ids=["no time zone", "not a time"])
def test_prune_keeps_an_artifact_whose_manifest_is_damaged_and_says_so(created, world,
                                                                       capsys):
    """Its age cannot be known: it is neither removed as old nor allowed to stop the prune;
    the command names it, and what to do, on its own line."""
    store = open_store(world["store"])
    alice, bob = world["keys"]["alice"], world["keys"]["bob"]
    path = Path(world["store"]) / "artifacts" / alice["poses"] / "manifest.json"
    doc = json.loads(path.read_text())
    path.write_text(json.dumps({**doc, "created": created}))
    removal = prune(store, datetime.now(UTC))
    # alice's page was made from her keyframes too: it goes with them.
    assert set(removal.artifacts) == {alice["video"], alice["keyframes"], alice["page"],
                                      *bob.values()}
    assert set(store.keys()) == {alice["poses"]}
    assert list(removal.damaged) == [alice["poses"]]
    assert "is not a valid manifest" in removal.damaged[alice["poses"]]
    for argv in (["--older-than-days", "0"], ["--unreferenced", "--older-than-days", "0",
                                              "--out", str(world["out"])]):
        assert main(["store", "prune", *argv, "--store", world["store"]]) == 0
        out = capsys.readouterr().out
        assert out.startswith("removed 0 artifacts"), out
        assert (f"kept a damaged artifact, whose age cannot be read: artifact {alice['poses']} "
                "is corrupt: file 'manifest.json' is not a valid manifest; delete ") in out
    assert set(store.keys()) == {alice["poses"]}


def test_prune_unreferenced_refuses_a_folder_without_results(world, tmp_path, capfd):
    """The dataset folder given as --out by mistake names no artifact: the whole store would
    go. A folder holding no report facecap wrote is refused, before anything is removed
    (a dry run too)."""
    from tests.test_bad_inputs import assert_one_line_error, facecap

    store = open_store(world["store"])
    before = set(store.keys())
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "report.json").write_text('{"title": "not a run report"}')
    for folder in (world["root"], tmp_path / "notes"):
        with pytest.raises(InputError) as refused:
            prune_unreferenced(store, [world["out"], folder], datetime.now(UTC))
        assert str(refused.value) == (f"{folder} holds no facecap results (no report.json "
                                      "under it); give the results folder the runs wrote (--out)")
        for dry_run in ([], ["--dry-run"]):
            code, _, err = facecap(capfd, "store", "prune", "--unreferenced", "--older-than-days",
                                   "0", "--out", folder, "--store", world["store"], *dry_run)
            assert_one_line_error(code, err, [f"{folder} holds no facecap results"])
    assert set(store.keys()) == before


@pytest.mark.parametrize("damage", ["not JSON", "unreadable"])
def test_prune_unreferenced_refuses_a_report_it_cannot_read(damage, world, capfd):
    """A run report under --out that cannot be read (or is no JSON) would let its run's
    artifacts go as unreferenced: the prune stops in one line before anything is removed
    (a link or a folder named report.json is none of facecap's and is passed over)."""
    from tests.test_bad_inputs import _run_without_dac_override, assert_one_line_error, facecap

    store = open_store(world["store"])
    before = set(store.keys())
    report = next(world["out"].rglob("report.json"))
    if damage == "not JSON":
        report.write_bytes(report.read_bytes()[:20])
    else:
        report.chmod(0)
    (world["out"] / "notes").mkdir()
    (world["out"] / "notes" / "report.json").symlink_to("/nonexistent")
    argv = ["store", "prune", "--unreferenced", "--older-than-days", "0", "--out",
            world["out"], "--store", world["store"]]
    if damage == "not JSON":
        code, _, err = facecap(capfd, *argv)
    else:  # in a process of its own: one that file modes bind, even run by root
        proc = _run_without_dac_override(argv)
        code, err = proc.returncode, proc.stderr
    assert_one_line_error(code, err, [str(report), "nothing was removed"])
    assert set(store.keys()) == before


def test_a_page_goes_with_its_face(world, tmp_path):
    """The pages kept for the UI's links show faces: a subject's capture pages and the
    dataset page that lists them go when the subject is forgotten; the page of an earlier
    run that no report names goes with a prune of what is unreferenced."""
    from facecap.pages.dataset import store_dataset_page

    store = open_store(world["store"])
    alice = world["keys"]["alice"]
    report = json.loads((world["out"] / "alice" / "take1" / "report.json").read_text())
    earlier = store_page(store, report, b"the page of alice's earlier run")
    # A result from before pages were kept, and one whose artifacts this store lacks.
    write_results(world["out"] / "alice" / "take0", {"report.json": json.dumps(
        {k: v for k, v in report.items() if k != "page"}).encode()})
    (world["out"] / "carol" / "take1").mkdir(parents=True)
    (world["out"] / "carol" / "take1" / "report.json").write_text(json.dumps(
        {"stages": {"poses": {"key": "poses-" + "0" * 32}}, "page": {"key": "../../x"}}))
    dataset = store_dataset_page(world["out"], store)
    # Made from every capture whose artifacts it shows (its faces), so forget finds it.
    assert store.manifest(dataset).inputs == {"alice/take0": alice["keyframes"],
                                              "alice/take1": alice["page"],
                                              "bob/take1": world["keys"]["bob"]["page"]}
    time.sleep(0.01)
    removal = prune_unreferenced(store, [world["out"]], datetime.now(UTC), dry_run=True)
    assert set(removal.artifacts) == {earlier, dataset}
    removal = forget(store, "alice", world["root"], world["out"])
    assert set(removal.artifacts) == {*alice.values(), earlier, dataset}


def test_forget_removes_only_what_facecap_wrote(world, tmp_path, capsys):
    """``OUT/SUBJECT`` may hold what facecap did not write: the user's notes, a result the
    user edited since, a link planted there. Only the files a results record names with the
    content facecap wrote go; the rest stays, listed; a link is never followed. A subject
    folder of notes alone loses nothing, and a planted report names no artifact to remove."""
    out, secret = world["out"], tmp_path / "secret.txt"
    secret.write_text("the user's own file")
    alice = out / "alice"
    (alice / "notes.txt").write_text("the user's notes about alice")
    write_results(alice / "take1", {"mesh.ply": b"a mesh facecap wrote",
                                    "preview.png": b"a preview facecap wrote"})
    (alice / "take1" / "preview.png").write_bytes(b"edited by the user since")
    (alice / "take1" / "linked.txt").symlink_to(secret)
    (alice / "take2").symlink_to(tmp_path, target_is_directory=True)
    # A report nobody recorded, naming bob's artifacts: it must not make them alice's.
    (alice / "take3").mkdir()
    (alice / "take3" / "report.json").write_text(json.dumps(
        {"stages": {k: {"key": v} for k, v in world["keys"]["bob"].items()}}))
    (out / "carol").mkdir()
    (out / "carol" / "notes.txt").write_text("carol's notes, no facecap result")
    code = main(["forget", "alice", "--out", str(out), "--store", world["store"]])
    printed = capsys.readouterr().out
    assert code == 0, printed
    store = open_store(world["store"])
    assert set(store.keys()) == set(world["keys"]["bob"].values())
    assert not (alice / "take1" / "mesh.ply").exists()
    assert not (alice / "take1" / "report.json").exists()
    assert (alice / "notes.txt").read_text() == "the user's notes about alice"
    assert (alice / "take1" / "preview.png").read_bytes() == b"edited by the user since"
    assert (alice / "take1" / "linked.txt").is_symlink() and (alice / "take2").is_symlink()
    assert (alice / "take3" / "report.json").is_file()
    assert secret.read_text() == "the user's own file" and (tmp_path / "secret.txt").is_file()
    assert "kept 5 entries" in printed and str(alice / "notes.txt") in printed
    main(["forget", "carol", "--out", str(out), "--store", world["store"]])
    assert (out / "carol" / "notes.txt").read_text() == "carol's notes, no facecap result"
    assert set(store.keys()) == set(world["keys"]["bob"].values())


@pytest.mark.parametrize("dry_run", [[], ["--dry-run"]], ids=["", "dry run"])
def test_forget_refuses_an_out_that_is_no_results_folder(dry_run, world, capfd):
    """``--out`` the dataset folder (the subject's raw captures would go), ``/`` (``/etc``
    was planned) or a folder in the store: one line, nothing removed. The dataset folder
    given as ``--out`` alone holds no record of a result: refused in one line, the captures
    stay."""
    from tests.test_bad_inputs import assert_one_line_error, facecap

    root, store = world["root"], world["store"]
    before = sorted(open_store(store).keys())
    for out, words in ((root, ["is the input folder"]), ("/", ["root of the file system"]),
                       (Path(store) / "artifacts", ["keeps for itself"])):
        code, _, err = facecap(capfd, "forget", "alice", "--root", root, "--out", out,
                               "--store", store, *dry_run)
        assert_one_line_error(code, err, words)
    code, _, err = facecap(capfd, "forget", "alice", "--out", root, "--store", store, *dry_run)
    assert_one_line_error(code, err, ["holds no record of a facecap result"])
    assert (root / "alice" / "take1.mp4").read_bytes() == b"the face of alice"
    assert (root / "alice" / "scan.ply").is_file()
    assert sorted(open_store(store).keys()) == before


def test_forget_makes_every_rewrite_before_it_removes_anything(world, tmp_path, capfd):
    """A damaged report.json elsewhere under OUT does not stop the dataset page from being
    written again without the subject; a summary that cannot be rewritten (the evaluation
    history a link out of OUT) stops the forget before anything is removed."""
    from facecap.pages.dataset import rewrite_dataset_page
    from tests.test_bad_inputs import assert_one_line_error, facecap

    out, store = world["out"], world["store"]
    write_results(out / "bob" / "take2", {"report.json": json.dumps(
        {"figures": {"keyframes": {"a": 1}, "metric_scale": "big", "roughness": [1]},
         "stages": []}).encode()})
    rewrite_dataset_page(out)
    assert "alice/take1" in (out / "index.html").read_text()
    history = tmp_path / "history"
    (out / "evaluations").rename(history)
    (out / "evaluations").symlink_to(history, target_is_directory=True)
    before = sorted(open_store(store).keys())
    code, _, err = facecap(capfd, "forget", "alice", "--out", out, "--store", store)
    assert_one_line_error(code, err, ["evaluations is a link"])
    assert sorted(open_store(store).keys()) == before
    assert (out / "alice" / "take1" / "report.json").is_file()
    (out / "evaluations").unlink()
    (out / "evaluations").mkdir()
    code, _, err = facecap(capfd, "forget", "alice", "--out", out, "--store", store)
    assert code == 0, err
    page = (out / "index.html").read_text()
    assert "alice/take1" not in page and "bob/take2" in page
    assert not (out / "alice").exists()


def test_forget_refuses_a_results_folder_without_records(world, capfd):
    """A subject's results written before facecap kept records (a mesh and a report, no
    ``.facecap-results.json``) cannot be shown to be facecap's: one line that says so and
    what to do, exit 2, and nothing removed, not the artifacts either."""
    out = world["out"]
    old = out / "alice" / "take1"
    (old / RECORD_NAME).unlink()  # as a run wrote it before facecap kept records
    (old / "mesh.ply").write_bytes(b"a mesh from before records")
    before = set(open_store(world["store"]).keys())
    code = main(["forget", "alice", "--out", str(out), "--store", world["store"]])
    err = capfd.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert "holds no record of a facecap result" in err[0] and "nothing was removed" in err[0]
    assert (old / "mesh.ply").read_bytes() == b"a mesh from before records"
    assert set(open_store(world["store"]).keys()) == before


@pytest.mark.parametrize("kind", ["FIFO", "deep"])
def test_planted_records_neither_hang_nor_crash_forget(kind, world, capfd):
    """A FIFO or JSON nested 100,000 deep planted as another subject's run report, as a
    results record in the subject's folder, as an evaluation and as ``dataset.json``: the
    forget used to hang (a FIFO opened to read) or end in a RecursionError, and one such
    file blocked the forget of every subject. Now the subject is forgotten, exit 0; the
    summaries it cannot read are kept, and named with what else the user must look at."""
    from facecap.pages.dataset import rewrite_dataset_page
    from tests.test_own_files import deadline, plant

    out, store = world["out"], world["store"]
    rewrite_dataset_page(out)  # the page forget rewrites without the subject
    planted = [out / "bob" / "take1" / "report.json", out / "alice" / "take1" / "x" / RECORD_NAME,
               out / "evaluations" / "20261102T020000000000Z.json", out / "dataset.json"]
    for path in planted:
        path.unlink(missing_ok=True)
        plant(path, kind, out)
    with deadline():
        code, printed, err = _forget(capfd, "alice", "--out", out, "--store", store, "--dry-run")
        assert code == 0, err
        code, printed, err = _forget(capfd, "alice", "--out", out, "--store", store)
    assert code == 0, err
    assert set(open_store(store).keys()) == set(world["keys"]["bob"].values())
    assert not (out / "alice" / "take1" / "report.json").exists()
    kept = printed[printed.index("kept "):]
    for path in planted[2:]:
        assert f"  {path}\n" in kept, printed
    # A regular file of a record's name is facecap's, whatever it holds: it goes; a FIFO stays.
    assert (f"  {planted[1]}\n" in kept) == (kind == "FIFO"), printed
    history = json.loads((out / "evaluations" / "20261101T020000000000Z.json").read_text())
    assert list(history["captures"]) == ["bob/take1"]
    assert "alice/take1" not in (out / "index.html").read_text()


def _forget(capfd, *argv) -> tuple[int, str, str]:
    code = main(["forget", *map(str, argv)])
    printed, err = capfd.readouterr()
    return code, printed, err


@pytest.mark.parametrize("kind", ["FIFO", "deep"])
def test_a_planted_report_neither_hangs_nor_crashes_a_prune(kind, world, capfd):
    """``store prune --unreferenced`` over a results folder with a FIFO ``report.json`` used
    to hang: a FIFO is none of facecap's reports and is passed over. A regular one nested
    100,000 deep used to end in a RecursionError: it is a damaged report, refused in one
    line before anything is removed."""
    from tests.test_bad_inputs import assert_one_line_error, facecap
    from tests.test_own_files import deadline, plant

    store = open_store(world["store"])
    before = set(store.keys())
    report = world["out"] / "carol" / "take1" / "report.json"
    plant(report, kind, world["out"])
    with deadline():
        code, _, err = facecap(capfd, "store", "prune", "--unreferenced", "--older-than-days",
                               "0", "--out", world["out"], "--store", world["store"])
    if kind == "FIFO":
        assert code == 0, err
    else:
        assert_one_line_error(code, err, [f"the run report {report} is damaged (JSON nested "
                                          "100000 deep", "nothing was removed"])
    assert set(store.keys()) == before


def test_forget_refuses_a_name_longer_than_a_folder_name(world, capfd):
    """A 300-character subject name used to reach the file system, whose ENAMETOOLONG came
    out as an internal error: one line, exit 2, nothing removed."""
    from tests.test_bad_inputs import assert_one_line_error, facecap

    before = set(open_store(world["store"]).keys())
    code, _, err = facecap(capfd, "forget", "a" * 300, "--root", world["root"], "--out",
                           world["out"], "--store", world["store"])
    assert_one_line_error(code, err, ["is 300 bytes long, longer than a folder name can be "
                                      "(255)", "give the name of a folder in the dataset"])
    assert set(open_store(world["store"]).keys()) == before
