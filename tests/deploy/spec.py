"""The deployment files as data: compose services, Dockerfile instructions, the package's
commands (the build context: dockerignore.py).

Tests read compose.yaml and the Dockerfile through this module, check them against the
package (entry points, the real argparse parsers, files in the repo), and turn a service's
container command into the same command on this host (`host_argv`).
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import io
import json
import re
import shlex
import sys
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from tests.procs import REPO

COMPOSE = REPO / "compose.yaml"
REVPI_OVERRIDE = REPO / "docker" / "compose.revpi.yaml"
PLANT_OVERRIDE = REPO / "docker" / "compose.plant.yaml"
ROUTER_OVERRIDE = REPO / "docker" / "compose.router.yaml"
DOCKERFILE = REPO / "Dockerfile"

_VAR = re.compile(r"\$\$|\$\{(?P<name>[A-Za-z_][A-Za-z0-9_]*)(?:(?P<op>:-|:\?)(?P<arg>[^}]*))?\}")


class SpecError(AssertionError):
    """A deployment file says something the package or the repo cannot honour."""


# ----------------------------------------------------------------------------- compose
def interpolate(text: str, env: Mapping[str, str]) -> str:
    """Compose's `${NAME}`, `${NAME:-default}`, `${NAME:?error}` and `$$` forms."""

    def one(m: re.Match[str]) -> str:
        if m[0] == "$$":  # a literal `$` (e.g. for a shell in the container)
            return "$"
        name, op, arg = m["name"], m["op"], m["arg"]
        value = env.get(name, "")
        if value:
            return value
        if op == ":-":
            return str(arg)
        if op == ":?":
            raise SpecError(f"${{{name}}} is required: {arg}")
        return ""

    return _VAR.sub(one, text)


def load_compose(path: Path = COMPOSE, env: Mapping[str, str] | None = None) -> dict[str, Any]:
    """The parsed file with variables interpolated in its strings (as compose does: after
    parsing, so a value keeps the type its quoting gave it)."""
    data = yaml.safe_load(path.read_text())
    if not isinstance(data, dict):
        raise SpecError(f"{path}: not a mapping")
    out: dict[str, Any] = _interpolate_tree(data, env or {})
    return out


def _interpolate_tree(node: Any, env: Mapping[str, str]) -> Any:
    if isinstance(node, str):
        return interpolate(node, env)
    if isinstance(node, list):
        return [_interpolate_tree(x, env) for x in node]
    if isinstance(node, dict):
        return {k: _interpolate_tree(v, env) for k, v in node.items()}
    return node


def merged(base: Mapping[str, Any], override: Mapping[str, Any]) -> dict[str, Any]:
    """`-f base -f override` as compose merges them, for the keys our files use: a service's
    `command` and other scalars replaced, its `volumes` appended, its `depends_on` and
    `environment` merged by name, new services and top-level `volumes` added."""
    out = copy.deepcopy(dict(base))
    services = out.setdefault("services", {})
    for name, svc in (override.get("services") or {}).items():
        mine = services.setdefault(name, {})
        for key, value in svc.items():
            if key == "volumes" and key in mine:
                mine[key] = [*mine[key], *value]
            elif key == "depends_on" and key in mine:
                both = {**depends_on(mine), **depends_on(svc)}
                mine[key] = {dep: {"condition": cond} for dep, cond in both.items()}
            elif key == "environment" and key in mine:
                mine[key] = {**environment(mine), **environment(svc)}
            else:
                mine[key] = copy.deepcopy(value)
    for key in ("volumes", "secrets"):
        if override.get(key):
            out[key] = {**(out.get(key) or {}), **override[key]}
    return out


def depends_on(svc: Mapping[str, Any]) -> dict[str, str]:
    """The service's dependencies → their condition (the short form's is service_started)."""
    deps = svc.get("depends_on") or {}
    if isinstance(deps, list):
        return dict.fromkeys(deps, "service_started")
    return {name: (cond or {}).get("condition", "service_started") for name, cond in deps.items()}


def service(compose: Mapping[str, Any], name: str) -> dict[str, Any]:
    services = compose.get("services") or {}
    if name not in services:
        raise SpecError(f"compose has no service {name!r} (has {sorted(services)})")
    svc: dict[str, Any] = services[name]
    return svc


def command(svc: Mapping[str, Any]) -> list[str]:
    """The service's command as an argv (exec form, or a string split like a shell)."""
    cmd = svc.get("command")
    if isinstance(cmd, str):
        return shlex.split(cmd)
    if not isinstance(cmd, list):
        raise SpecError(f"command is neither a list nor a string: {cmd!r}")
    return [str(x) for x in cmd]


def healthcheck_argv(svc: Mapping[str, Any]) -> list[str]:
    """`healthcheck.test` as an argv: `[CMD, …]` or `[CMD-SHELL, "…"]`."""
    test = (svc.get("healthcheck") or {}).get("test")
    if not isinstance(test, list) or not test:
        raise SpecError(f"healthcheck.test must be a non-empty list, got {test!r}")
    kind, *rest = (str(x) for x in test)
    if kind == "CMD":
        return rest
    if kind == "CMD-SHELL":
        return ["sh", "-c", " ".join(rest)]
    raise SpecError(f"healthcheck.test must start with CMD or CMD-SHELL, got {kind!r}")


_HEARTBEAT_CHECK = re.compile(r"find (?P<path>\S+) -mmin -(?P<minutes>[0-9.]+) \| grep -q \.")


def heartbeat_freshness_s(check: str, path: str) -> float:
    """The age in seconds up to which a heartbeat check (`find PATH -mmin -M | grep -q .`)
    passes; SpecError if `check` is not that command on `path`."""
    m = _HEARTBEAT_CHECK.fullmatch(check.strip())
    if m is None or m["path"] != path:
        raise SpecError(f"not a heartbeat check of {path}: {check!r}")
    return float(m["minutes"]) * 60.0


def environment(svc: Mapping[str, Any]) -> dict[str, str]:
    env = svc.get("environment") or {}
    if isinstance(env, list):
        return dict(str(e).split("=", 1) for e in env)
    return {str(k): str(v) for k, v in env.items()}


@dataclass(frozen=True)
class Mount:
    """One `volumes:` entry: a bind mount (source is a path) or a named volume."""

    source: str
    target: str
    read_only: bool

    @property
    def is_bind(self) -> bool:
        return self.source.startswith(("./", "../", "/"))


def mounts(svc: Mapping[str, Any]) -> list[Mount]:
    out = []
    for entry in svc.get("volumes") or []:
        if not isinstance(entry, str):
            raise SpecError(f"use the short volume syntax SRC:DST[:ro], got {entry!r}")
        parts = entry.split(":")
        if len(parts) not in (2, 3):
            raise SpecError(f"volume {entry!r} is not SRC:DST[:ro]")
        out.append(Mount(parts[0], parts[1], len(parts) == 3 and "ro" in parts[2].split(",")))
    return out


def seconds(duration: str | int | float) -> float:
    """Compose durations such as `10s`, `1m30s`, `500ms`."""
    if isinstance(duration, int | float):
        return float(duration)
    units = {"ms": 0.001, "s": 1.0, "m": 60.0, "h": 3600.0}
    parts = re.findall(r"(\d+(?:\.\d+)?)(ms|s|m|h)", duration)
    if not parts or "".join(n + u for n, u in parts) != duration:
        raise SpecError(f"not a duration: {duration!r}")
    return sum(float(n) * units[u] for n, u in parts)


# -------------------------------------------------------------------------- Dockerfile
@dataclass(frozen=True)
class Instruction:
    keyword: str
    args: str
    stage: int
    """Index of the build stage (the FROM) the instruction belongs to."""


def dockerfile(path: Path = DOCKERFILE) -> list[Instruction]:
    """Instructions with line continuations joined and comments dropped."""
    out: list[Instruction] = []
    stage = -1
    pending = ""
    for raw in path.read_text().splitlines():
        line = raw.strip()
        if line.startswith("#") or (not line and not pending):
            continue
        if line.endswith("\\"):
            pending += line[:-1] + " "
            continue
        full = (pending + line).strip()
        pending = ""
        if not full:
            continue
        keyword, _, args = full.partition(" ")
        keyword = keyword.upper()
        if keyword == "FROM":
            stage += 1
        out.append(Instruction(keyword, args.strip(), stage))
    if pending:
        raise SpecError(f"{path}: ends inside a line continuation")
    return out


def exec_form(args: str) -> list[str]:
    """A JSON-array (exec form) argument list; shell form is refused."""
    try:
        value = json.loads(args)
    except ValueError as exc:
        raise SpecError(f"not exec (JSON array) form: {args!r}") from exc
    if not isinstance(value, list) or not all(isinstance(x, str) for x in value):
        raise SpecError(f"not a JSON array of strings: {args!r}")
    return value


def split_options(args: str) -> tuple[dict[str, str], str]:
    """`--interval=10s --retries=3 CMD [...]` → ({interval: 10s, retries: 3}, `CMD [...]`)."""
    options: dict[str, str] = {}
    rest = args
    while rest.startswith("--"):
        option, _, rest = rest.partition(" ")
        name, _, value = option[2:].partition("=")
        options[name] = value
        rest = rest.lstrip()
    return options, rest


def image(instructions: Sequence[Instruction], target: str | None = None) -> list[Instruction]:
    """What an image is built from: the instructions of the `target` stage (default the last,
    which a build without --target makes) after those of the stages it is `FROM`, in order."""
    names: dict[str, int] = {}
    bases: dict[int, str] = {}
    for i in instructions:
        if i.keyword == "FROM":
            parts = re.split(r"\s+as\s+", i.args, flags=re.I)
            base = parts[0].split()[-1]
            if len(parts) == 2:
                names[parts[1].strip()] = i.stage
            bases[i.stage] = base
    if target is None:
        stage = max(bases)
    elif target in names:
        stage = names[target]
    else:
        raise SpecError(f"no stage {target!r} in the Dockerfile ({sorted(names)})")
    chain = [stage]
    while bases[chain[0]] in names:
        chain.insert(0, names[bases[chain[0]]])
    return [i for s in chain for i in instructions if i.stage == s]


def image_args(
    instructions: Sequence[Instruction], keyword: str, target: str | None = None
) -> list[str]:
    """The arguments of each `keyword` instruction an image is built from (`image`)."""
    return [i.args for i in image(instructions, target) if i.keyword == keyword]


def image_env(instructions: Sequence[Instruction], target: str | None = None) -> dict[str, str]:
    """An image's ENV settings (`ENV A=1 \\ B=2` form)."""
    out: dict[str, str] = {}
    for args in image_args(instructions, "ENV", target):
        out.update(dict(pair.split("=", 1) for pair in shlex.split(args)))
    return out


# ------------------------------------------------------------------------------ package
def pyproject() -> dict[str, Any]:
    return tomllib.loads((REPO / "pyproject.toml").read_text())


def entry_points() -> dict[str, str]:
    """Console script name → module (`machine` → `service.cli`)."""
    scripts: dict[str, str] = pyproject()["project"]["scripts"]
    return {name: target.partition(":")[0] for name, target in scripts.items()}


def parse_cli(argv: Sequence[str]) -> argparse.Namespace:
    """Parse a `machine …` or `rider …` command line with the package's own parsers, the way
    their `main()` does (including `rider ui`'s and `rider gateway`'s own options); raise
    SpecError if it fails."""
    if not argv:
        raise SpecError("empty command")
    program, args = argv[0], list(argv[1:])
    scripts = entry_points()
    if program not in scripts:
        raise SpecError(f"{program!r} is not an entry point of the package ({sorted(scripts)})")
    if program == "machine":
        from ride_machine.service.cli import build_parser as machine_parser

        return _parse(machine_parser(), args, argv)
    from ride_machine.rider.cli import build_parser as rider_parser

    ns, rest = _parse_known(rider_parser(), args, argv)
    if ns.cmd == "ui":
        from ride_machine.rider.ui.app import build_parser as ui_parser

        ns.ui = _parse(ui_parser(), rest, argv)
    elif ns.cmd == "gateway":
        from ride_machine.rider.gateway.cli import build_parser as gateway_parser

        ns.gateway = _parse(gateway_parser(), rest, argv)
    elif rest:
        raise SpecError(f"{shlex.join(argv)}: unrecognized arguments {rest}")
    return ns


def _parse(
    parser: argparse.ArgumentParser, args: list[str], argv: Sequence[str]
) -> argparse.Namespace:
    ns, rest = _parse_known(parser, args, argv)
    if rest:
        raise SpecError(f"{shlex.join(argv)}: unrecognized arguments {rest}")
    return ns


def _parse_known(
    parser: argparse.ArgumentParser, args: list[str], argv: Sequence[str]
) -> tuple[argparse.Namespace, list[str]]:
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err):
            return parser.parse_known_args(args)
    except SystemExit as exc:
        raise SpecError(f"{shlex.join(argv)} does not parse: {err.getvalue().strip()}") from exc


def host_argv(
    argv: Sequence[str], paths: Mapping[str, Path], python: str = sys.executable
) -> list[str]:
    """A container command as the same command here: an entry point runs as `python -m
    module`, `python` is this interpreter, and container paths become host paths."""
    scripts = entry_points()
    head = argv[0]
    if head in scripts:
        prefix = [python, "-m", scripts[head]]
    elif head == "python":
        prefix = [python]
    else:
        raise SpecError(f"{head!r} is neither an entry point nor python")
    return prefix + [host_path(a, paths) for a in argv[1:]]


def host_path(arg: str, paths: Mapping[str, Path]) -> str:
    """`arg` with a container path (a mount target, or a file below one) replaced."""
    for target, host in paths.items():
        if arg == target:
            return str(host)
        if arg.startswith(target.rstrip("/") + "/"):
            return str(host / arg[len(target.rstrip("/")) + 1 :])
    return arg


SECRETS_DIR = "/run/secrets"


def secret_paths(
    compose: Mapping[str, Any], svc: Mapping[str, Any], host_dir: Path
) -> dict[str, Path]:
    """Container path → host path of each secret a service gets (`/run/secrets/<name>`), the
    host file named as in the top-level `secrets:` (`file: ./secrets/…`) but under `host_dir`."""
    declared = compose.get("secrets") or {}
    out = {}
    for name in svc.get("secrets") or []:
        if name not in declared:
            raise SpecError(f"secret {name!r} is not declared at the top level")
        out[f"{SECRETS_DIR}/{name}"] = host_dir / Path(declared[name]["file"]).name
    return out


def mount_paths(
    svc: Mapping[str, Any], volumes_dir: Path, replace: Mapping[str, Path] | None = None
) -> dict[str, Path]:
    """Container path → host path for a service: bind mounts from the repo (or `replace`d by
    source), named volumes as directories under `volumes_dir`."""
    out: dict[str, Path] = {}
    for m in mounts(svc):
        if m.is_bind:
            out[m.target] = (replace or {}).get(m.source) or (REPO / m.source).resolve()
        else:
            out[m.target] = volumes_dir / m.source
            out[m.target].mkdir(parents=True, exist_ok=True)
    return out
