"""The service stack: docker-compose.yml, the worker image and deploy/prefect.yaml.

One module on purpose (~600 lines): the stack is one configuration, checked against itself
(every variable a container reads is one the stack sets) in one place.

No Docker engine runs here: Debian's ``docker-compose`` (1.29) validates and resolves the
compose file offline, and deploy/prefect.yaml is registered on a live local Prefect server,
where a process worker runs the nightly deployment the way the stack's workers do.
"""

from __future__ import annotations

import ast
import base64
import fnmatch
import os
import re
import shutil
import subprocess
import sys
import time
import tomllib
from datetime import datetime
from pathlib import Path
from zoneinfo import ZoneInfo

import httpx
import pytest
import yaml

from tests.servers import free_port, stop, wait_until_healthy

ROOT = Path(__file__).resolve().parents[1]
COMPOSE_FILE = ROOT / "docker-compose.yml"
DOCKERFILE = ROOT / "deploy" / "Dockerfile"
PREFECT_YAML = ROOT / "deploy" / "prefect.yaml"
ENV_EXAMPLE = ROOT / ".env.example"
PREFECT_BIN = Path(sys.executable).with_name("prefect")

SERVICES = {"postgres", "server", "minio", "minio-init", "deployments", "worker", "conductor"}

# A test .env with values that are easy to find again in the resolved configuration.
TEST_ENV = {
    "POSTGRES_USER": "facecap_pg_user",
    "POSTGRES_PASSWORD": "pg-password-7c1f",
    "POSTGRES_DB": "facecap_pg_db",
    "MINIO_ROOT_USER": "minio-root-user",
    "MINIO_ROOT_PASSWORD": "minio-root-password-2b9e",
    "AWS_ACCESS_KEY_ID": "facecap-worker-key",
    "AWS_SECRET_ACCESS_KEY": "worker-secret-5d3a",
    "PREFECT_API_AUTH_STRING": "admin:prefect-password-9e4c",
    "FACECAP_S3_BUCKET": "facecap-test-bucket",
    "FACECAP_WORKERS": "3",
}
SECRETS = ["POSTGRES_PASSWORD", "MINIO_ROOT_PASSWORD", "AWS_SECRET_ACCESS_KEY",
           "PREFECT_API_AUTH_STRING"]
# The containers that may hold each secret; every other one must not.
SECRET_HOLDERS = {
    "POSTGRES_PASSWORD": {"postgres", "server"},
    "MINIO_ROOT_PASSWORD": {"minio", "minio-init"},
    "AWS_SECRET_ACCESS_KEY": {"minio-init", "worker", "conductor"},
    "PREFECT_API_AUTH_STRING": {"server", "deployments", "worker", "conductor"},
}
SECRET_NAME = re.compile(r"PASSWORD|SECRET|AUTH_STRING|TOKEN|ACCESS_KEY", re.IGNORECASE)

DEPLOYMENTS = {
    # deployment name: (entrypoint, parameters it must accept)
    "reconstruct-capture": ("flows/capture.py:reconstruct_capture", {"video", "out", "config"}),
    "reconstruct-dataset": ("flows/dataset.py:reconstruct_dataset", {"root", "out", "config"}),
    "nightly-evaluation": ("flows/evaluate.py:evaluate_dataset", {"root", "out"}),
}


# --------------------------------------------------------------------------- helpers


def docker_compose() -> str:
    found = shutil.which("docker-compose")
    if found is None:
        pytest.fail("docker-compose not found: run `make system-libs` "
                    "(apt-get install docker-compose)")
    return found


def run_compose_config(project: Path, env: dict[str, str], *args: str):
    """`docker-compose config` on a copy of the stack whose .env holds ``env``."""
    project.mkdir(parents=True, exist_ok=True)
    shutil.copy(COMPOSE_FILE, project / "docker-compose.yml")
    (project / "deploy").mkdir(exist_ok=True)
    shutil.copy(DOCKERFILE, project / "deploy" / "Dockerfile")
    (project / ".env").write_text("".join(f"{key}={value}\n" for key, value in env.items()))
    # Only PATH and HOME: variables of the calling shell would override the .env file.
    clean = {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "HOME": str(project)}
    return subprocess.run(
        [docker_compose(), "-f", "docker-compose.yml", "config", *args],
        cwd=project, env=clean, capture_output=True, text=True, timeout=120,
    )


@pytest.fixture(scope="module")
def resolved(tmp_path_factory) -> dict:
    """The compose configuration resolved with TEST_ENV."""
    result = run_compose_config(tmp_path_factory.mktemp("stack"), TEST_ENV)
    assert result.returncode == 0, result.stderr
    return yaml.safe_load(result.stdout)


def service_env(config: dict, service: str) -> dict[str, str]:
    environment = config["services"][service].get("environment") or {}
    if isinstance(environment, list):
        environment = dict(item.split("=", 1) for item in environment)
    return {key: str(value) for key, value in environment.items()}


def environment_blocks(raw: dict):
    for name, service in raw["services"].items():
        yield name, service.get("environment") or {}


def read_env_file(path: Path) -> dict[str, str]:
    values = {}
    for line in path.read_text().splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            key, _, value = line.partition("=")
            values[key.strip()] = value.strip()
    return values


def dockerfile_instructions() -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) of deploy/Dockerfile, continuation lines joined."""
    text = re.sub(r"\\\n", " ", DOCKERFILE.read_text())
    instructions = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            word, _, rest = line.partition(" ")
            instructions.append((word.upper(), " ".join(rest.split())))
    return instructions


def load_prefect_yaml() -> dict:
    return yaml.safe_load(PREFECT_YAML.read_text())


def env_placeholders(value) -> set[str]:
    return set(re.findall(r"\{\{\s*\$(\w+)\s*\}\}", yaml.safe_dump(value)))


# --------------------------------------------------------------------------- compose file


def test_compose_file_validates_offline(tmp_path):
    result = run_compose_config(tmp_path, TEST_ENV, "-q")
    assert result.returncode == 0, result.stderr


def test_env_example_holds_every_variable_and_only_placeholders(tmp_path):
    example = read_env_file(ENV_EXAMPLE)
    # Every secret is a placeholder, never a usable value.
    for key in SECRETS + ["POSTGRES_USER", "MINIO_ROOT_USER", "AWS_ACCESS_KEY_ID"]:
        assert key in example, f"{key} missing from .env.example"
    for key in SECRETS:
        assert "change-me" in example[key], f"{key} in .env.example is not a placeholder"
    # A copy of the example is a complete .env: nothing the stack requires is missing.
    result = run_compose_config(tmp_path, example, "-q")
    assert result.returncode == 0, result.stderr


@pytest.mark.parametrize("missing", SECRETS)
def test_a_missing_credential_stops_compose(tmp_path, missing):
    env = {key: value for key, value in TEST_ENV.items() if key != missing}
    result = run_compose_config(tmp_path, env, "-q")
    assert result.returncode != 0
    assert f"set {missing} in .env" in result.stderr


def test_the_stack_has_its_services_wired_together(resolved):
    services = resolved["services"]
    assert set(services) == SERVICES

    server = services["server"]
    assert server["image"] == "prefecthq/prefect:3.9.1-python3.11"
    assert "4200" in str(server["ports"])
    db_url = service_env(resolved, "server")["PREFECT_API_DATABASE_CONNECTION_URL"]
    assert db_url == (
        "postgresql+asyncpg://facecap_pg_user:pg-password-7c1f@postgres:5432/facecap_pg_db"
    )
    for name in ("postgres", "server", "minio"):
        assert services[name]["healthcheck"]["test"], f"{name} has no healthcheck"
    assert services["server"]["depends_on"]["postgres"]["condition"] == "service_healthy"
    assert services["minio-init"]["depends_on"]["minio"]["condition"] == "service_healthy"
    assert services["deployments"]["depends_on"]["server"]["condition"] == "service_healthy"

    worker = services["worker"]
    assert worker["build"]["dockerfile"] == "deploy/Dockerfile"
    assert worker["depends_on"]["server"]["condition"] == "service_healthy"
    assert worker["depends_on"]["minio-init"]["condition"] == "service_completed_successfully"
    assert worker["deploy"]["replicas"] == 3  # FACECAP_WORKERS from .env
    command = " ".join(worker["command"])
    assert "prefect worker start --pool facecap --type process --work-queue captures" in command
    conductor = services["conductor"]
    assert "--work-queue default" in " ".join(conductor["command"])
    assert service_env(resolved, "conductor") == service_env(resolved, "worker")
    assert "set-concurrency-limit facecap" in " ".join(services["deployments"]["command"])
    env = service_env(resolved, "worker")
    assert env["PREFECT_API_URL"] == "http://server:4200/api"
    assert env["FACECAP_STORE"] == "s3://facecap-test-bucket/artifacts"
    assert env["AWS_ENDPOINT_URL_S3"] == "http://minio:9000"
    assert env["AWS_ACCESS_KEY_ID"] == "facecap-worker-key"


def test_state_lives_in_named_volumes(resolved):
    volumes = set(resolved["volumes"])
    assert {"postgres-data", "minio-data", "facecap-home", "facecap-output"} <= volumes
    mounted = {
        name: {str(v).split(":")[0] for v in service.get("volumes", [])}
        for name, service in resolved["services"].items()
    }
    assert "postgres-data" in mounted["postgres"]
    assert "minio-data" in mounted["minio"]
    assert {"facecap-home", "facecap-output"} <= mounted["worker"]
    assert mounted["conductor"] == mounted["worker"]


def test_each_container_gets_only_the_credentials_it_needs(resolved):
    for secret, holders in SECRET_HOLDERS.items():
        value = TEST_ENV[secret]
        having = {
            name for name in resolved["services"]
            if any(value in v for v in service_env(resolved, name).values())
        }
        assert having == holders, f"{secret} reaches {sorted(having)}"


def test_compose_file_holds_no_literal_secret():
    raw_text = COMPOSE_FILE.read_text()
    raw = yaml.safe_load(raw_text)
    for name, environment in environment_blocks(raw):
        for key, value in environment.items():
            if SECRET_NAME.search(key):
                assert re.fullmatch(r"\$\{\w+:\?[^}]*\}", str(value)), (
                    f"{name}.{key} must be a required ${{VAR:?...}} reference, not a value"
                )
    db_url = raw["services"]["server"]["environment"]["PREFECT_API_DATABASE_CONNECTION_URL"]
    assert ":${POSTGRES_PASSWORD:?" in db_url
    for secret in SECRETS:
        assert TEST_ENV[secret] not in raw_text
    assert "env_file" not in raw_text  # no container receives the whole .env


def _refuse_placeholders_entry() -> list[str]:
    """The containers' entry as the shell gets it (Compose turns ``$$`` into ``$``)."""
    raw = yaml.safe_load(COMPOSE_FILE.read_text())
    return [part.replace("$$", "$") for part in raw["x-refuse-placeholders"]]


def test_every_container_starts_through_the_placeholder_check(resolved):
    entry = resolved["services"]["worker"]["entrypoint"]
    assert entry[:2] == ["/bin/sh", "-c"] and "change-me" in entry[2]
    for name, service in resolved["services"].items():
        assert service.get("entrypoint") == entry, f"{name} starts without the check"
        assert service.get("command"), f"{name} has no command for the check to run"


def test_a_placeholder_secret_stops_a_container_and_a_real_one_starts_it():
    """The entry itself, run by sh with a service's command: any variable still holding a
    value of .env.example stops it with one line naming the variables, not their values."""
    entry = _refuse_placeholders_entry()
    example = read_env_file(ENV_EXAMPLE)
    base = {"PATH": os.environ.get("PATH", "/usr/bin:/bin")}
    placeholders = {key: example[key] for key in SECRETS}
    stopped = subprocess.run([*entry, "echo", "started"], env={**base, **placeholders},
                             capture_output=True, text=True, timeout=30)
    assert stopped.returncode == 1 and stopped.stdout == ""
    [line] = stopped.stderr.strip().splitlines()
    assert line.startswith("refusing to start:") and "put real secrets into .env" in line
    for key, value in placeholders.items():
        assert key in line and value not in line
    url = {"PREFECT_API_DATABASE_CONNECTION_URL":
           f"postgresql+asyncpg://prefect:{example['POSTGRES_PASSWORD']}@postgres:5432/prefect"}
    inside_url = subprocess.run([*entry, "echo", "started"], env={**base, **url},
                                capture_output=True, text=True, timeout=30)
    assert inside_url.returncode == 1 and "PREFECT_API_DATABASE_CONNECTION_URL" in inside_url.stderr
    started = subprocess.run([*entry, "echo", "started", "with  two spaces"],
                             env={**base, **{key: TEST_ENV[key] for key in SECRETS}},
                             capture_output=True, text=True, timeout=30)
    assert started.returncode == 0 and started.stdout == "started with  two spaces\n"


def test_the_workers_s3_account_may_use_only_the_artifacts_bucket(resolved):
    """minio-init gives the workers' account a policy over FACECAP_S3_BUCKET alone (no
    admin, no other bucket); the workers never get MinIO's root account."""
    import json

    script = resolved["services"]["minio-init"]["command"][-1]
    policy = json.loads(re.search(r"<<POLICY\n(.*?)\n\s*POLICY", script, re.S).group(1)
                        .replace("$$FACECAP_S3_BUCKET", "facecap-test-bucket"))
    resources = {r for statement in policy["Statement"] for r in statement["Resource"]}
    assert resources == {"arn:aws:s3:::facecap-test-bucket", "arn:aws:s3:::facecap-test-bucket/*"}
    actions = {a for statement in policy["Statement"] for a in statement["Action"]}
    assert all(a.startswith("s3:") and "*" not in a for a in actions)
    assert not {"s3:DeleteBucket", "s3:PutBucketPolicy", "s3:CreateBucket"} & actions
    assert "--user \"$$AWS_ACCESS_KEY_ID\"" in script
    worker = service_env(resolved, "worker")
    assert TEST_ENV["MINIO_ROOT_PASSWORD"] not in worker.values()
    assert worker["FACECAP_INPUT_ROOTS"] == "/data/datasets"
    assert worker["FACECAP_OUTPUT_ROOT"] == "/data/output"


def test_env_file_never_reaches_git_or_the_image():
    def ignored(patterns: list[str]) -> bool:
        matched = False
        for pattern in patterns:
            negated = pattern.startswith("!")
            if fnmatch.fnmatch(".env", pattern.lstrip("!").lstrip("/")):
                matched = not negated
        return matched

    def patterns(path: Path) -> list[str]:
        return [line.strip() for line in path.read_text().splitlines()
                if line.strip() and not line.startswith("#")]

    assert ignored(patterns(ROOT / ".gitignore")), ".env is not in .gitignore"
    assert ignored(patterns(ROOT / ".dockerignore")), ".env is not in .dockerignore"


# --------------------------------------------------------------------------- worker image


def test_worker_image_installs_the_project_as_a_non_root_user():
    instructions = dockerfile_instructions()
    words = [word for word, _ in instructions]
    assert instructions[0] == ("FROM", "python:3.11-slim")
    run_lines = [args for word, args in instructions if word == "RUN"]
    assert any("apt-get install" in r and "libusb-1.0-0" in r and "libgomp1" in r
               for r in run_lines)
    install = next(i for i, (w, a) in enumerate(instructions)
                   if w == "RUN" and re.search(r"pip install -c deploy/constraints.txt \.(\s|$)", a))
    # The exact versions of the tested environment, copied in before the install that uses them.
    assert any(w == "COPY" and re.search(r"(^|\s)deploy/?(\s|$)", a)
               for w, a in instructions[:install])
    constraints = (ROOT / "deploy" / "constraints.txt").read_text().splitlines()
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    prefect_pin = next(d for d in pyproject["project"]["dependencies"] if d.startswith("prefect=="))
    assert prefect_pin in constraints
    # mediapipe (the face detector) is installed apart, --no-deps: one version everywhere.
    makefile = re.search(r"^MEDIAPIPE := (mediapipe==\S+)$", (ROOT / "Makefile").read_text(),
                         re.M).group(1)
    assert makefile in constraints
    assert any(f"--no-deps {makefile}" in a for w, a in instructions if w == "RUN")
    users = [i for i, (w, a) in enumerate(instructions) if w == "USER"]
    assert users and users[-1] > install
    assert instructions[users[-1]][1] not in ("root", "0")
    assert words[-1] in ("CMD", "ENTRYPOINT")
    assert "prefect" in instructions[-1][1] and "facecap" in instructions[-1][1]

    # Every package of the project, and the README pyproject names, is copied in.
    copied = " ".join(args for word, args in instructions if word == "COPY")
    setuptools = pyproject["tool"]["setuptools"]
    folders = {setuptools["package-dir"].get(p, p.replace(".", "/")) for p in setuptools["packages"]}
    for folder in {f.split("/")[0] for f in folders}:
        assert re.search(rf"(^|\s){folder}/?(\s|$)", copied), f"{folder} not copied"
    assert pyproject["project"]["readme"] in copied

    # No credential is baked in.
    for word, args in instructions:
        if word in ("ENV", "ARG"):
            assert not SECRET_NAME.search(args), f"{word} {args}"


# --------------------------------------------------------------------------- prefect.yaml


def test_prefect_yaml_declares_the_three_deployments():
    config = load_prefect_yaml()
    deployments = {d["name"]: d for d in config["deployments"]}
    assert set(deployments) == set(DEPLOYMENTS)
    for name, (entrypoint, _) in DEPLOYMENTS.items():
        assert deployments[name]["entrypoint"] == entrypoint
        assert deployments[name]["work_pool"]["name"] == "facecap"
        assert deployments[name]["enforce_parameter_schema"] is True
    (step,) = config["pull"]
    directory = step["prefect.deployments.steps.set_working_directory"]["directory"]
    assert env_placeholders(directory) == {"FACECAP_PROJECT_DIR"}
    # The image provides that directory and holds the project there.
    instructions = dockerfile_instructions()
    envs = " ".join(args for word, args in instructions if word == "ENV")
    workdir = [args for word, args in instructions if word == "WORKDIR"][-1]
    assert f"FACECAP_PROJECT_DIR={workdir}" in envs


def test_nightly_schedule_takes_its_time_zone_from_the_environment(monkeypatch):
    from prefect.client.schemas.schedules import CronSchedule
    from prefect.utilities.templating import apply_values

    nightly = next(d for d in load_prefect_yaml()["deployments"]
                   if d["name"] == "nightly-evaluation")
    (schedule,) = nightly["schedules"]
    assert schedule["cron"] == "0 2 * * *"
    monkeypatch.setenv("FACECAP_NIGHTLY_TIMEZONE", "America/New_York")
    resolved_schedule = apply_values(schedule, {})
    cron = CronSchedule(cron=resolved_schedule["cron"], timezone=resolved_schedule["timezone"])
    assert cron.timezone == "America/New_York"
    monkeypatch.setenv("FACECAP_NIGHTLY_TIMEZONE", "Mars/Olympus_Mons")
    with pytest.raises(ValueError):
        CronSchedule(cron="0 2 * * *", timezone=apply_values(schedule, {})["timezone"])


def test_compose_deploy_job_sets_what_prefect_yaml_reads(resolved):
    deployments = load_prefect_yaml()["deployments"]
    needed = set().union(*(env_placeholders(d) for d in deployments))
    assert needed == {"FACECAP_DATASET_ROOT", "FACECAP_OUTPUT_ROOT", "FACECAP_NIGHTLY_TIMEZONE"}
    env = service_env(resolved, "deployments")
    assert needed <= set(env)
    assert env["FACECAP_NIGHTLY_TIMEZONE"] == "UTC"  # the default when .env does not set it
    command = " ".join(resolved["services"]["deployments"]["command"])
    assert "env -u FACECAP_PROJECT_DIR" in command
    assert "deploy --all --prefect-file deploy/prefect.yaml" in command


def flow_parameters(entrypoint: str) -> set[str]:
    """Parameter names of the @flow function an entrypoint names, read from its source."""
    path, function = entrypoint.split(":")
    tree = ast.parse((ROOT / path).read_text())
    for node in tree.body:
        if isinstance(node, ast.FunctionDef) and node.name == function:
            decorators = [ast.unparse(d) for d in node.decorator_list]
            assert any(d == "flow" or d.startswith("flow(") for d in decorators), (
                f"{entrypoint} is not decorated with @flow"
            )
            arguments = node.args.posonlyargs + node.args.args + node.args.kwonlyargs
            return {a.arg for a in arguments}
    raise AssertionError(f"{path} defines no function {function}")


@pytest.mark.parametrize("name", DEPLOYMENTS)
def test_entrypoints_name_flows_with_the_documented_parameters(name):
    entrypoint, parameters = DEPLOYMENTS[name]
    assert (ROOT / entrypoint.split(":")[0]).is_file(), f"{entrypoint}: no such file"
    assert parameters <= flow_parameters(entrypoint)


# --------------------------------------------------------------------------- live server

AUTH = "admin:deploy-test-password"


def prefect_env(home: Path, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("PREFECT_", "FACECAP_", "AWS_"))}
    env.update(PREFECT_HOME=str(home), PREFECT_SERVER_ANALYTICS_ENABLED="false", **extra)
    return env


@pytest.fixture(scope="module")
def live_server(tmp_path_factory):
    """A local Prefect server with basic auth, on SQLite; yields its API URL."""
    home = tmp_path_factory.mktemp("prefect-server")
    port = free_port()
    env = prefect_env(
        home,
        PREFECT_SERVER_API_AUTH_STRING=AUTH,
        PREFECT_UI_ENABLED="false",
        PREFECT_SERVER_SERVICES_SCHEDULER_LOOP_SECONDS="2",
    )
    log = open(home / "server.log", "w")
    server = subprocess.Popen(
        [str(PREFECT_BIN), "server", "start", "--host", "127.0.0.1", "--port", str(port)],
        env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
    )
    api = f"http://127.0.0.1:{port}/api"
    try:
        wait_until_healthy(api, server, home / "server.log")
        yield api
    finally:
        stop(server)
        log.close()


def api_client(api: str) -> httpx.Client:
    token = base64.b64encode(AUTH.encode()).decode()
    return httpx.Client(base_url=api, headers={"Authorization": f"Basic {token}"}, timeout=30)


def prefect_cli(args: list[str], env: dict[str, str], cwd: Path) -> None:
    result = subprocess.run([str(PREFECT_BIN), *args], env=env, cwd=cwd,
                            capture_output=True, text=True, timeout=300)
    output = result.stdout[-3000:] + result.stderr[-3000:]
    assert result.returncode == 0, f"prefect {' '.join(args)}:\n{output}"


@pytest.mark.slow
def test_prefect_yaml_deploys_and_a_worker_runs_the_nightly_evaluation(live_server, tmp_path):
    client = api_client(live_server)
    assert httpx.post(f"{live_server}/deployments/filter", json={}).status_code == 401

    # Register as the compose `deployments` job does, FACECAP_PROJECT_DIR unset.
    cli_env = prefect_env(tmp_path / "cli-home", PREFECT_API_URL=live_server,
                          PREFECT_API_AUTH_STRING=AUTH, FACECAP_NIGHTLY_TIMEZONE="Europe/Berlin",
                          FACECAP_DATASET_ROOT="/data/datasets", FACECAP_OUTPUT_ROOT="/data/output")
    created = client.post("/work_pools/", json={"name": "facecap", "type": "process"})
    assert created.status_code == 201, created.text
    prefect_cli(["--no-prompt", "deploy", "--all", "--prefect-file", "deploy/prefect.yaml"],
                cli_env, ROOT)

    registered = {d["name"]: d for d in client.post("/deployments/filter", json={}).json()}
    assert set(registered) == set(DEPLOYMENTS)
    for name, (entrypoint, parameters) in DEPLOYMENTS.items():
        deployment = registered[name]
        assert deployment["entrypoint"] == entrypoint
        assert deployment["work_pool_name"] == "facecap"
        assert parameters <= set(deployment["parameter_openapi_schema"]["properties"])
        # Still a placeholder: each worker fills in its own checkout.
        assert deployment["pull_steps"] == [{"prefect.deployments.steps.set_working_directory":
                                             {"directory": "{{ $FACECAP_PROJECT_DIR }}"}}]
    nightly = registered["nightly-evaluation"]
    assert nightly["parameters"] == {"root": "/data/datasets", "out": "/data/output"}
    (schedule,) = nightly["schedules"]
    assert schedule["active"]
    assert schedule["schedule"]["cron"] == "0 2 * * *"
    assert schedule["schedule"]["timezone"] == "Europe/Berlin"

    # The scheduler plans nightly runs at 02:00 Berlin time.
    run_filter = {"deployments": {"id": {"any_": [nightly["id"]]}},
                  "flow_runs": {"state": {"type": {"any_": ["SCHEDULED"]}}}}
    deadline = time.monotonic() + 60
    while not (scheduled := client.post("/flow_runs/filter", json=run_filter).json()):
        assert time.monotonic() < deadline, "the nightly deployment got no scheduled runs"
        time.sleep(1)
    for run in scheduled:
        start = datetime.fromisoformat(run["expected_start_time"].replace("Z", "+00:00"))
        local = start.astimezone(ZoneInfo("Europe/Berlin"))
        assert (local.hour, local.minute) == (2, 0)

    # The server checks parameters against the flow's schema (enforce_parameter_schema).
    for bad in ({"root": ["/x"], "out": "/y"}, {"root": "/x", "out": "/y", "tolerance_mm": "high"}):
        refused = client.post(f"/deployments/{nightly['id']}/create_flow_run",
                              json={"parameters": bad})
        assert refused.status_code == 409, refused.text

    # A worker started elsewhere runs a flow from its own checkout via the pull step.
    dataset = tmp_path / "dataset"
    (dataset / "subject_a").mkdir(parents=True)
    (dataset / "subject_a" / "take1.mp4").write_bytes(b"")  # no scan: evaluation skips it
    output = tmp_path / "output"
    run = client.post(f"/deployments/{nightly['id']}/create_flow_run",
                      json={"parameters": {"root": str(dataset), "out": str(output)}})
    assert run.status_code == 201, run.text
    # A run that names a dataset outside the worker's input roots fails at its start.
    escape = client.post(f"/deployments/{nightly['id']}/create_flow_run",
                         json={"parameters": {"root": str(ROOT), "out": str(output)}})
    assert escape.status_code == 201, escape.text
    worker_dir = tmp_path / "elsewhere"
    worker_dir.mkdir()
    worker_env = prefect_env(tmp_path / "worker-home", PREFECT_API_URL=live_server,
                             PREFECT_API_AUTH_STRING=AUTH, FACECAP_PROJECT_DIR=str(ROOT),
                             FACECAP_HOME=str(tmp_path / "facecap-home"),
                             FACECAP_STORE=str(tmp_path / "store"),
                             FACECAP_INPUT_ROOTS=str(dataset), FACECAP_OUTPUT_ROOT=str(output),
                             PREFECT_WORKER_QUERY_SECONDS="1")
    worker_log = open(tmp_path / "worker.log", "w")
    worker = subprocess.Popen(
        [str(PREFECT_BIN), "worker", "start", "--pool", "facecap", "--type", "process",
         "--limit", "1"],
        env=worker_env, cwd=worker_dir, stdout=worker_log, stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 180
        final = ("COMPLETED", "FAILED", "CRASHED", "CANCELLED")
        while True:
            state = client.get(f"/flow_runs/{run.json()['id']}").json()["state"]
            refused = client.get(f"/flow_runs/{escape.json()['id']}").json()["state"]
            if state["type"] in final and refused["type"] in final:
                break
            assert time.monotonic() < deadline, f"flow runs still {state['type']}, {refused['type']}"
            time.sleep(1)
    finally:
        stop(worker)  # before the server stops, or the worker hangs
        worker_log.close()
    assert state["type"] == "COMPLETED", (
        f"{state['type']}: {state.get('message')}\n{(tmp_path / 'worker.log').read_text()[-3000:]}"
    )
    assert refused["type"] == "FAILED"
    assert "outside the folders this service reads from" in refused["message"], refused
    (evaluation,) = (output / "evaluations").glob("*.json")
    assert '"subject_a/take1"' in evaluation.read_text()  # listed as skipped: it has no scan
