"""The Docker image's install, replayed: no container engine runs here, so the build stage of
docker/Dockerfile is read (its COPY and RUN pip lines, whatever they say today) and run in a new
virtual environment, then the image's command serves and its health check and a Blend answer."""
from __future__ import annotations

import json
import os
import re
import shlex
import shutil

import pytest

from tests.install._install import ROOT, Venv, check_bare_server, copy_sources, hint, serving

pytestmark = pytest.mark.install

DOCKERFILE = os.path.join(ROOT, "docker", "Dockerfile")


def instructions(path: str = DOCKERFILE) -> list[tuple[str, str]]:
    """``(INSTRUCTION, arguments)`` in order, continuation lines joined, comments dropped."""
    out, pending = [], ""
    with open(path) as f:
        for line in f:
            stripped = line.strip()
            if not pending and (not stripped or stripped.startswith("#")):
                continue
            if stripped.endswith("\\"):
                pending += stripped[:-1] + " "
                continue
            text = pending + stripped
            pending = ""
            word, _, rest = text.partition(" ")
            out.append((word.upper(), rest.strip()))
    return out


def build_stage(steps):
    """The instructions of the first stage (the one that installs), up to the next FROM."""
    froms = [i for i, (word, _) in enumerate(steps) if word == "FROM"]
    return steps[froms[0] + 1:froms[1]]


def test_the_image_install_serves_without_extras(tmp_path):
    steps = instructions()
    stage = build_stage(steps)
    workdir = next(a for w, a in stage if w == "WORKDIR")
    args = dict(re.fullmatch(r'(\w+)(?:=(.*))?', a).groups() for w, a in stage if w == "ARG")
    env = {k: (v or "").strip('"') for k, v in args.items()}
    venv_line = next(a for w, a in stage if w == "RUN" and re.search(r"-m venv\b", a))
    image_venv = shlex.split(venv_line)[-1]
    runs = [a for w, a in stage if w == "RUN" and re.search(r"\bpip\b", a)]
    assert runs, "the Dockerfile's build stage installs nothing with pip"

    # The image's absolute paths, here: the venv, the sources, and where pip writes wheels.
    src, venv = str(tmp_path / "src"), Venv(str(tmp_path / "venv"))
    places = {image_venv: venv.path, workdir: src}
    for run in runs:
        for d in re.findall(r"(?:-w|--wheel-dir)[ =](\S+)", run):
            places[d] = str(tmp_path / d.strip("/").replace("/", "_"))
    for word, a in stage:
        if word == "COPY":
            *sources, dest = shlex.split(a)
            sources = [os.path.normpath(s) for s in sources]
            assert os.path.normpath(dest) in (".", *sources), f"COPY {a}: not into the same place"
            copy_sources(src, sources)
    assert os.path.isfile(os.path.join(src, "setup.py")), "the build stage copies no setup.py"

    def local(command: str) -> str:
        known = "|".join(re.escape(p) for p in sorted(places, key=len, reverse=True))
        pattern = rf"(?<![\w.$/-])({known})(?=[/\s\"']|$)"
        unknown = re.findall(r"(?<![\w.$/-])/[\w.-]+", re.sub(pattern, "HERE", command))
        assert not unknown, f"the replay does not know where {unknown} is: {command}"
        return re.sub(pattern, lambda m: places[m.group(1)], command)

    for run in runs:
        venv.run("bash", "-ec", local(run), cwd=src, timeout=1200, env_extra=env)

    # The runtime stage's command, with a free loopback port instead of 0.0.0.0:50051.
    runtime = steps[[i for i, (w, _) in enumerate(steps) if w == "FROM"][1] + 1:]
    entry = json.loads(next(a for w, a in runtime if w == "ENTRYPOINT"))
    cmd = json.loads(next(a for w, a in runtime if w == "CMD"))
    assert entry == ["dqpose"] and cmd[0] == "serve", (entry, cmd)
    check = json.loads(next(a for w, a in runtime if w == "HEALTHCHECK").split("CMD", 1)[1])
    cwd = str(tmp_path / "run")
    os.makedirs(cwd)
    with serving(venv, *cmd[1:], "--host", "127.0.0.1", "--port", "0", cwd=cwd) as address:
        target = check.index("--server") + 1
        health = venv.run(*check[:target], address, *check[target + 1:], cwd=cwd)
        assert health.stdout.strip() == "SERVING"
        check_bare_server(address, hint("planning", "dqpose"))
    shutil.rmtree(src)
