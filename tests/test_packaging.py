"""The base install is a light client: ``pip install arcloud`` brings numpy, httpx, protobuf and OpenCV
(the client's frame codecs), and everything else (the service, the simulator, datasets, Zenoh) comes
with an extra (``server``, ``sim``, ``datasets``, ``events``; ``all`` is every one, what ``make``
installs).

Three checks, fastest first: the dependency lists in pyproject.toml; the client, run in this
environment, loads only third-party modules that the base dependencies install; and (slow, about 15 s
with pip's local indexes) the project installed with no extra into a fresh virtual environment, where
the heavy packages do not import, sends a frame to a real service and reads the map back.
"""

from __future__ import annotations

import importlib.metadata
import json
import os
import shutil
import socket
import subprocess
import sys
import time
import tomllib
from collections.abc import Iterator
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

PROJECT_ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((PROJECT_ROOT / "pyproject.toml").read_text())["project"]

BASE = {"numpy", "httpx", "protobuf", "opencv-python-headless"}
#: Packages the base install must not bring (each one's import name).
HEAVY = {"open3d": "open3d", "onnxruntime": "onnxruntime", "fastapi": "fastapi", "redis": "redis", "eclipse-zenoh": "zenoh",
         "scipy": "scipy", "pydantic": "pydantic", "uvicorn": "uvicorn", "tqdm": "tqdm"}  # fmt: skip
EXTRAS = {"events", "server", "sim", "datasets", "all", "dev"}

#: Run in the environment under test: exercises the client (frame codecs, protobuf, HTTP; the
#: service's URL in argv[1], or none for the codecs only) and prints what it saw as JSON.
CLIENT_SCRIPT = """
import sys
at_start = set(sys.modules)
import dataclasses, importlib, json
import numpy as np
from arcloud.client import ArcloudClient, frame_body, subscribe

heavy = json.loads(sys.argv[2])
importable = []
for name in heavy:
    try:
        importlib.import_module(name)
        importable.append(name)
    except ImportError:
        pass
rgb = np.full((120, 160, 3), 90, np.uint8)
depth = np.full((120, 160), 2.0, np.float32)
frame = dict(map_id="light", rgb=rgb, depth=depth, intrinsics=(130.0, 130.0, 79.5, 59.5), cam2world=np.eye(4),
             device_id="light-client", frame_id="f0")
frame_body(**frame)
frame_body(**frame, rgb_encoding="png")
out = {"importable": importable}
if sys.argv[1]:
    with ArcloudClient(sys.argv[1]) as client:
        out["sent"] = dataclasses.asdict(client.send_frame(**frame))
        out["frames"] = client.wait_until_processed("light", 1, timeout_s=30)["frames"]
        out["objects"] = [dataclasses.asdict(o) for o in client.list_objects("light", include_tentative=True)]
    try:
        subscribe("light", print, ["tcp/127.0.0.1:9"]).close()
    except ImportError as exc:
        out["subscribe_error"] = str(exc)
out["loaded"] = sorted({n.split(".")[0] for n in set(sys.modules) - at_start} - set(sys.stdlib_module_names) - {"arcloud"})
print(json.dumps(out))
"""


def names(requirements: list[str]) -> set[str]:
    return {canonicalize_name(Requirement(r).name) for r in requirements}


def pinned() -> set[str]:
    lines = (PROJECT_ROOT / "constraints.txt").read_text().splitlines()
    return {canonicalize_name(line.split("==")[0]) for line in lines if "==" in line and not line.startswith("#")}


def test_base_dependencies_are_the_light_client() -> None:
    assert names(PYPROJECT["dependencies"]) == BASE


def test_extras_hold_the_rest_and_all_holds_every_extra() -> None:
    extras = PYPROJECT["optional-dependencies"]
    assert set(extras) == EXTRAS
    assert names(extras["events"]) == {"eclipse-zenoh"}
    assert {"fastapi", "uvicorn", "redis", "onnxruntime", "scipy", "pydantic-settings", "eclipse-zenoh"} <= names(
        extras["server"]
    )
    assert {"open3d", "scipy", "tqdm"} <= names(extras["sim"]) and {"open3d", "scipy", "onnxruntime"} <= names(extras["datasets"])
    (everything,) = extras["all"]
    assert Requirement(everything).name == "arcloud" and Requirement(everything).extras == EXTRAS - {"all", "dev"}
    heavy = {canonicalize_name(h) for h in HEAVY}
    assert heavy <= set().union(*(names(extras[e]) for e in ("events", "server", "sim", "datasets")))


def test_every_dependency_is_pinned_in_constraints() -> None:
    requirements = [*PYPROJECT["dependencies"], *(r for rs in PYPROJECT["optional-dependencies"].values() for r in rs)]
    missing = names([r for r in requirements if not r.startswith("arcloud[")]) - pinned()
    assert not missing, f"not in constraints.txt: {sorted(missing)}"


def base_closure() -> set[str]:
    """The distributions the base dependencies may bring: transitively, markers evaluated here, and
    their own extras counted (httpx imports click and pygments when they are there, for its CLI)."""
    seen: set[str] = set()
    todo = [Requirement(r) for r in PYPROJECT["dependencies"]]
    while todo:
        requirement = todo.pop()
        name = canonicalize_name(requirement.name)
        if name in seen or (requirement.marker is not None and not requirement.marker.evaluate({"extra": ""})):
            continue
        seen.add(name)
        try:
            metadata = importlib.metadata.metadata(requirement.name)
        except importlib.metadata.PackageNotFoundError:  # an extra's package that is not installed
            continue
        extras = ["", *(metadata.get_all("Provides-Extra") or [])]
        for line in importlib.metadata.requires(requirement.name) or []:
            dependency = Requirement(line)
            if dependency.marker is None or any(dependency.marker.evaluate({"extra": e}) for e in extras):
                dependency.marker = None
                todo.append(dependency)
    return seen


def test_the_client_loads_only_what_the_base_dependencies_install() -> None:
    """Here every extra is installed, so a module the client loads by mistake would import: the check
    is on what it loads, each module mapped to its distribution."""
    done = subprocess.run([sys.executable, "-c", CLIENT_SCRIPT, "", "[]"], capture_output=True, text=True, timeout=60, check=True)
    loaded = json.loads(done.stdout)["loaded"]
    distributions = importlib.metadata.packages_distributions()
    by = {canonicalize_name(d) for module in loaded for d in distributions.get(module, [module])}
    assert by <= base_closure(), f"the client loads {sorted(by - base_closure())}, not installed by the base dependencies"


# --- the light install itself ---------------------------------------------------------------------
OFFLINE_SIGNS = ("No matching distribution found", "Could not find a version", "NewConnectionError", "Temporary failure in name resolution", "Network is unreachable")  # fmt: skip


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """The real service (``arcloud serve``, embedded, simulated detector) from this environment."""
    import httpx

    port = free_port()
    url = f"http://127.0.0.1:{port}"
    command = [
        sys.executable,
        "-m",
        "arcloud.cli",
        "serve",
        "--host",
        "127.0.0.1",
        "--port",
        str(port),
        "--detector",
        "sim:0",
        "--workers",
        "1",
    ]
    env = {k: v for k, v in os.environ.items() if not k.startswith("ARCLOUD_")}
    log = tmp_path_factory.mktemp("serve") / "serve.log"
    with log.open("w") as log_file:
        process = subprocess.Popen(command, env=env, stdout=log_file, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                if httpx.get(f"{url}/readyz", timeout=1).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if process.poll() is not None or time.monotonic() > deadline:
                pytest.fail(f"arcloud serve did not become ready: {log.read_text()[-2000:]}")
            time.sleep(0.1)
        yield url
    finally:
        process.terminate()  # also when it died: then a no-op
        try:
            process.wait(20)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def install_light(tmp_path: Path) -> Path:
    """The project's wheel (built from a copy of its sources) installed with no extra, constraints.txt's
    versions, into a new virtual environment; its python. pip runs from this environment (``pip --python``)."""
    source = tmp_path / "source"
    shutil.copytree(PROJECT_ROOT / "src", source / "src", ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    for name in ("pyproject.toml", "README.md", "constraints.txt"):
        shutil.copy2(PROJECT_ROOT / name, source / name)
    build = [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(tmp_path / "dist"), str(source)]
    try:  # the build backend from here when it is recent enough: no isolated build environment to fill
        import setuptools

        if int(setuptools.__version__.split(".")[0]) >= 70:
            build.insert(-1, "--no-build-isolation")
    except ImportError:
        pass
    subprocess.run(build, check=True, timeout=300, capture_output=True)
    (wheel,) = (tmp_path / "dist").glob("arcloud-*.whl")
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=60)
    python = venv / "bin" / "python"
    install = [
        sys.executable,
        "-m",
        "pip",
        "--python",
        str(python),
        "install",
        "-q",
        "-c",
        str(source / "constraints.txt"),
        str(wheel),
    ]
    done = subprocess.run(install, capture_output=True, text=True, timeout=300)
    if done.returncode != 0:
        output = done.stdout + done.stderr
        if any(sign in output for sign in OFFLINE_SIGNS):
            pytest.skip(f"pip could not get the base dependencies (no index reachable?): {output.strip()[-500:]}")
        raise AssertionError(f"pip install of the base package failed:\n{output[-3000:]}")
    return python


@pytest.mark.slow
def test_the_base_install_is_a_client_that_talks_to_the_service(tmp_path: Path, service: str) -> None:
    started = time.perf_counter()
    python = install_light(tmp_path)
    install_s = time.perf_counter() - started
    done = subprocess.run([str(python), "-c", CLIENT_SCRIPT, service, json.dumps(sorted(HEAVY.values()))],
                          capture_output=True, text=True, timeout=120, cwd=tmp_path, env={"PATH": os.environ.get("PATH", "")})  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    out = json.loads(done.stdout)
    assert out["importable"] == [], f"the base install brought {out['importable']} (install took {install_s:.1f} s)"
    assert out["sent"]["status"] == "queued" and out["sent"]["map_id"] == "light"
    assert out["frames"]["processed"] == 1 and out["frames"]["failed"] == 0
    assert isinstance(out["objects"], list)
    assert "pip install 'arcloud[events]'" in out["subscribe_error"]
    assert not set(out["loaded"]) & set(HEAVY.values())

    cli = subprocess.run([str(python.parent / "arcloud"), "--help"], capture_output=True, text=True, timeout=60)
    assert cli.returncode == 0 and cli.stdout.startswith("usage: arcloud"), cli.stderr[-2000:]
