"""A dataset spread over a work pool against the same dataset in one process.

    python benchmarks/bench_pool.py [--out out/bench_pool] [--workers 2] [--until evaluation]

Renders four short synthetic captures (ICT identities 3 and 4, two takes each, 640×360,
30 fps, 4 s) into OUT/dataset, starts a Prefect server, registers ``deploy/prefect.yaml`` on
a process pool and starts WORKERS ``prefect worker`` processes; then reconstructs the
dataset twice, each time into an empty store of its own so that nothing is reused:

* **pool** — a run of the ``reconstruct-dataset`` deployment: one ``reconstruct-capture``
  run per capture on the workers, as many at once as the capture deployment's limit allows;
* **in-process** — ``facecap dataset`` on the same server: one capture after another.

Prints both wall times, the most capture runs that ran at once, and writes OUT/report.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CAPTURES = [("ict3", "take1", "ict:3", 1), ("ict3", "take2", "ict:3", 2),
            ("ict4", "take1", "ict:4", 3), ("ict4", "take2", "ict:4", 4)]
CONFIG = {"mvs": {"views": {"num_sources": 6}, "depth": {"processing_width": 480}}}


def render(root: Path) -> None:
    from facecap.synthetic import synthesize
    from facecap.synthetic.config import SynthConfig

    for subject, take, identity, seed in CAPTURES:
        video = root / subject / f"{take}.mp4"
        if video.is_file():
            continue
        with tempfile.TemporaryDirectory() as tmp:
            print(f"rendering {subject}/{take} ...", flush=True)
            synthesize(SynthConfig(subject=identity, width=640, height=360, fps=30,
                                   duration_s=4, seed=seed), Path(tmp), progress=False)
            video.parent.mkdir(parents=True, exist_ok=True)
            (Path(tmp) / "video.mp4").replace(video)


def start(args: list[str], env: dict, log: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "prefect", *args], env=env, cwd=REPO,
                            stdout=log.open("w"), stderr=subprocess.STDOUT)


def prefect(args: list[str], env: dict) -> None:
    subprocess.run([sys.executable, "-m", "prefect", *args], env=env, cwd=REPO, check=True,
                   capture_output=True, timeout=300)


def main() -> Path:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/bench_pool"))
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--until", default="evaluation")
    parser.add_argument("--port", type=int, default=4271)
    a = parser.parse_args()
    out = a.out.resolve()
    root = out / "dataset"
    render(root)
    config = out / "config.json"
    config.write_text(json.dumps(CONFIG))
    url = f"http://127.0.0.1:{a.port}/api"
    env = {k: v for k, v in os.environ.items() if not k.startswith(("FACECAP_", "PREFECT_"))}
    env.update(PREFECT_HOME=str(out / "prefect"), PREFECT_API_URL=url,
               PREFECT_SERVER_ANALYTICS_ENABLED="false", PREFECT_WORKER_QUERY_SECONDS="5")
    server = start(["server", "start", "--port", str(a.port)], env, out / "server.log")
    workers = []
    try:
        for _ in range(240):
            try:
                urllib.request.urlopen(f"{url}/health", timeout=1)
                break
            except OSError:
                time.sleep(0.5)
        prefect(["work-pool", "create", "facecap", "--type", "process", "--overwrite"], env)
        prefect(["work-pool", "set-concurrency-limit", "facecap", str(a.workers + 1)], env)
        prefect(["--no-prompt", "deploy", "--all", "--prefect-file", "deploy/prefect.yaml"],
                {**env, "FACECAP_DATASET_ROOT": str(root), "FACECAP_OUTPUT_ROOT": str(out),
                 "FACECAP_NIGHTLY_TIMEZONE": "UTC"})
        worker_env = {**env, "FACECAP_PROJECT_DIR": str(REPO), "FACECAP_INPUT_ROOTS": str(out),
                      "FACECAP_OUTPUT_ROOT": str(out), "FACECAP_STORE": str(out / "store_pool")}
        workers = [start(["worker", "start", "--pool", "facecap", "--type", "process",
                          "--limit", "2", "--name", f"bench{i}"], worker_env,
                         out / f"worker{i}.log") for i in range(a.workers)]
        from prefect.deployments import run_deployment
        from prefect.settings import PREFECT_API_URL, temporary_settings

        with temporary_settings({PREFECT_API_URL: url}):
            t0 = time.perf_counter()
            dataset = run_deployment(
                "reconstruct-dataset/reconstruct-dataset", timeout=7200, poll_interval=5,
                as_subflow=False, parameters={"root": str(root), "out": str(out / "pool"),
                                              "config": CONFIG, "until": a.until})
            pool_s = time.perf_counter() - t0
        at_once = json.loads((out / "pool" / "dataset.json").read_text())["captures_at_once"]
        print(f"pool: {dataset.state.name}, {pool_s:.0f} s wall, {at_once} captures at once",
              flush=True)
        t0 = time.perf_counter()
        serial = subprocess.run([sys.executable, "-m", "facecap", "dataset", str(root),
                                 "--out", str(out / "serial"), "--config", str(config)],
                                env={**env, "FACECAP_STORE": str(out / "store_serial")},
                                cwd=REPO)
        serial_s = time.perf_counter() - t0
        print(f"in-process: exit {serial.returncode}, {serial_s:.0f} s wall", flush=True)
    finally:
        for process in workers + [server]:
            process.terminate()
            try:
                process.wait(30)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(30)
    report = {"captures": len(CAPTURES), "workers": a.workers, "until": a.until,
              "pool_state": dataset.state.name, "pool_wall_s": round(pool_s, 1),
              "captures_at_once": at_once, "in_process_exit": serial.returncode,
              "in_process_wall_s": round(serial_s, 1), "cpu_count": os.cpu_count()}
    path = out / "report.json"
    path.write_text(json.dumps(report, indent=1))
    print(json.dumps(report))
    return path


if __name__ == "__main__":
    main()
