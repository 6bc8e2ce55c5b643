"""The checker behind tests/test_readme.py: the README and the docs/ pages name only things that exist.

Checked in README.md and docs/*.md (inline code, links, and the commands of ```bash blocks):
- `adamimic <command> ...`: a bash block's command line must parse with pipeline/cli.py's own parser (command,
  flags, required arguments, value types); in inline code the command and each `--flag` must exist.
- `make <target>`: a target of the Makefile.
- `python [-m module | script.py] --flag`: the module or script exists, and a stage script (stages/*.py) parses
  its arguments with the stages' parser; any other script or module holds each flag as a string literal.
- Repository paths, in inline code or as link targets: tracked by git, or produced by a stage (an `outs`,
  `metrics` or `plots` path of dvc.yaml, or inside one), or made by `make setup` (.venv/, .cache/,
  robots/g1/vendor/). `<task>`, `*` and `${...}` match any one path segment. A path counts as one of the
  repository's when it starts at one of its top-level entries (`pipeline/`, `docs/`, `data/`, `results/`, ...);
  others are relative to something the text names (`meta/info.json` inside a dataset) and are not checked,
  nor are paths outside the repository (`../`), absolute paths, URLs, git's own `.git/`, and the folder a
  command is told to write (`--out X`).
- `python -m module` is checked when the module is one of the repository's (`pipeline.…`), not pytest's or pip's.
- Link anchors into markdown files (`RESULTS.md#where-it-stands`): a heading of that file.
- params.yaml keys (`env.rewards.sigma2.feet_pos`, `dvc exp run -S key=...`, `--set key=...`): a field of the
  typed config dataclasses (pipeline/config.py's sections; `tasks.<name>.` resolves in TaskConfig).
- ```yaml blocks that are params.yaml text (its sections, or entries of `tasks:`) pass the sections' validation.
"""

from __future__ import annotations

import argparse
import dataclasses
import fnmatch
import re
import shlex
import subprocess
import typing
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
SETUP_OUTPUTS = (".venv", ".cache", "robots/g1/vendor")
SECTIONS = {"retarget": "pipeline.retarget.config:RetargetConfig", "env": "pipeline.envs.config:EnvConfig",
            "train": "pipeline.rl.config:TrainConfig", "evaluate": "pipeline.evaluation.config:EvalConfig",
            "tasks": "pipeline.keyframes.config:TaskConfig"}
TOP_LEVEL_SCALARS = ("profile", "variants")
KEY = re.compile(r"^(retarget|env|train|evaluate|tasks)(\.[\w<>{}*,-]+)+$")
FENCE = re.compile(r"^```(\w*)\s*$")


# ------------------------------------------------------------------------------------------ reading pages
def split_page(text: str) -> tuple[list[str], list[str], list[str], list[str]]:
    """(inline code spans outside fences, link targets, command lines of bash blocks, yaml blocks)."""
    spans, links, commands, yamls = [], [], [], []
    prose, block, lang = [], None, ""
    for line in text.splitlines():
        fence = FENCE.match(line.strip())
        if fence and block is None:
            block, lang = [], fence.group(1)
            continue
        if line.strip() == "```" and block is not None:
            if lang in ("bash", "sh", "shell", ""):
                commands += _commands(block)
            elif lang in ("yaml", "yml"):
                yamls.append("\n".join(block))
            block = None
            continue
        if block is not None:
            block.append(line)
        else:
            prose.append(line)
    body = "\n".join(prose)
    spans = re.findall(r"`([^`\n]+)`", body)
    links = re.findall(r"\]\(([^)\s]+)\)", body)
    return spans, links, commands, yamls


def _commands(lines: list[str]) -> list[str]:
    joined, out = "", []
    for line in lines:
        line = re.sub(r"(^|\s)#.*$", "", line).rstrip()  # comments
        if line.endswith("\\"):
            joined += line[:-1] + " "
            continue
        joined += line
        out += [part.strip() for part in re.split(r"&&|;|\|", joined) if part.strip()]
        joined = ""
    return out


# ------------------------------------------------------------------------------------------ what exists
def tracked_paths() -> set[str]:
    try:
        files = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout: which paths are tracked is unknown")
    paths = set(files)
    for f in files:  # and every folder that holds a tracked file
        parts = f.split("/")
        paths.update("/".join(parts[:k]) for k in range(1, len(parts)))
    return paths


def dvc_outputs() -> list[list[str]]:
    spec = yaml.safe_load((ROOT / "dvc.yaml").read_text())
    outs = []
    for stage in spec["stages"].values():
        stage = stage.get("do", stage)
        for kind in ("outs", "metrics", "plots"):
            for item in stage.get(kind, []) or []:
                path = item if isinstance(item, str) else next(iter(item))
                outs.append(_segments(path))
    return outs


def _segments(path: str) -> list[str]:
    return ["*" if re.search(r"[<>*{}$]", seg) else seg for seg in path.strip("/").split("/")]


def _seg_match(a: str, b: str) -> bool:
    return a == "*" or b == "*" or fnmatch.fnmatch(a, b) or fnmatch.fnmatch(b, a)


def path_problem(path: str, tracked: set[str], outputs: list[list[str]]) -> str | None:
    path = path.split("#")[0].rstrip("/")
    if not path or path.startswith(("../", "/")) or "://" in path or path.startswith("mailto:"):
        return None
    if any(path == s or path.startswith(s + "/") for s in SETUP_OUTPUTS):
        return None
    segs = _segments(path)
    if segs[0] == ".git" or (segs[0] not in {t.split("/")[0] for t in tracked} | {o[0] for o in outputs}):
        return None  # not the repository's: relative to something else the text names
    segs = _segments(path)
    if "*" not in segs and path in tracked:
        return None
    if "*" in segs and any(len(t.split("/")) == len(segs) and all(map(_seg_match, segs, t.split("/")))
                           for t in tracked):
        return None
    if any(len(segs) >= len(out) and all(map(_seg_match, segs[:len(out)], out)) for out in outputs):
        return None
    return f"path `{path}` is neither tracked nor a stage's output"


def looks_like_path(token: str) -> bool:
    return ("/" in token and " " not in token and "=" not in token and not token.startswith("-")
            and "$" not in token and "://" not in token
            and not re.match(r"[^./]+\.[^/]*/", token)  # `module.attr/other`: names, not a path
            and re.fullmatch(r"[\w.<>{}*,@-]+(/[\w.<>{}*,@-]*)+", token) is not None)


def anchors(markdown: Path) -> set[str]:
    """GitHub's heading anchors: lower case, punctuation dropped, spaces to hyphens."""
    out = set()
    in_fence = False
    for line in markdown.read_text().splitlines():
        if line.strip().startswith("```"):
            in_fence = not in_fence
        if not in_fence and (m := re.match(r"^#{1,6}\s+(.*?)\s*#*$", line)):
            out.add(re.sub(r"[^\w\- ]", "", m.group(1).lower()).replace(" ", "-"))
    return out


def key_problem(key: str) -> str | None:
    """None when `key` (dotted, params.yaml) names a field of the typed configs."""
    import importlib

    parts = key.split(".")
    if parts[0] in TOP_LEVEL_SCALARS and len(parts) == 1:
        return None
    if parts[0] not in SECTIONS:
        return f"params key `{key}`: no section {parts[0]!r}"
    module, name = SECTIONS[parts[0]].split(":")
    cls = getattr(importlib.import_module(module), name)
    rest = parts[2:] if parts[0] == "tasks" else parts[1:]  # tasks.<name>.field
    for k, part in enumerate(rest):
        if not (dataclasses.is_dataclass(cls) and isinstance(cls, type)):
            return f"params key `{key}`: {'.'.join(parts[:len(parts) - len(rest) + k])} has no sub-keys"
        fields = {f.name for f in dataclasses.fields(cls)}
        names = [n for n in fields if fnmatch.fnmatch(n, part.replace("{", "[").replace("}", "]").replace(",", ""))]
        if not names:
            return f"params key `{key}`: {cls.__name__} has no field {part!r}"
        cls = typing.get_type_hints(cls).get(names[0])
    return None


def yaml_problem(block: str) -> str | None:
    """None when a yaml block is valid params.yaml text: whole sections, or task entries (a `tasks:` excerpt)."""
    from pipeline.common.errors import PipelineInputError
    from pipeline.config import TOP_LEVEL_KEYS, resolve_task_templates
    from pipeline.envs.config import EnvConfig
    from pipeline.evaluation.config import EvalConfig
    from pipeline.keyframes.task_parsing import load_tasks
    from pipeline.retarget.config import RetargetConfig
    from pipeline.rl.config import TrainConfig

    try:
        raw = yaml.safe_load(block)
    except yaml.YAMLError as error:
        return f"yaml block does not parse: {error}"
    if not isinstance(raw, dict):
        return None
    if set(raw) <= set(TOP_LEVEL_KEYS):
        sections = raw
    elif all(isinstance(v, dict) and ("input" in v or "extends" in v) for v in raw.values()):
        sections = {"tasks": raw}  # an excerpt of `tasks:`
    else:
        return None  # not params.yaml text
    parsers = {"retarget": RetargetConfig.from_dict, "env": EnvConfig.from_dict, "train": TrainConfig.from_dict,
               "evaluate": EvalConfig.from_dict, "tasks": lambda t: load_tasks(resolve_task_templates(t, "README"))}
    try:
        for name, value in sections.items():
            if name in parsers:
                parsers[name](value)
    except PipelineInputError as error:
        return f"yaml block: {error}"
    return None


# ------------------------------------------------------------------------------------------ commands
class Parsed(BaseException):
    """Raised instead of running the command, once argparse accepted its arguments (a BaseException, so that
    no `except Exception` in the command swallows it)."""


def cli_problem(argv: list[str], monkeypatch, capsys, full: bool) -> str | None:
    """None when `adamimic <argv>` parses (full) or, for a fragment in prose, its command and flags exist."""
    from pipeline import cli

    if not full:
        flags = [a.split("=")[0] for a in argv[1:] if a.startswith("--")]
        argv = argv[:1] + ["--help"]
    original = argparse.ArgumentParser.parse_args

    def parse_only(self, args=None, namespace=None):
        raise Parsed(original(self, args, namespace))

    with monkeypatch.context() as patch:
        patch.setattr(argparse.ArgumentParser, "parse_args", parse_only)
        try:
            cli.main(argv)
        except Parsed:
            return None
        except SystemExit as stop:
            out = capsys.readouterr()
            if full and stop.code == 0 and ("--help" in argv or "-h" in argv):
                return None
            if not full and stop.code == 0:
                missing = [f for f in flags if not re.search(rf"(^|[\s,]){re.escape(f)}\b", out.out)]
                return f"`adamimic {argv[0]}` has no option {missing[0]}" if missing else None
            return f"`adamimic {' '.join(argv)}` does not parse: {out.err.strip().splitlines()[-1:]}"
    return f"`adamimic {' '.join(argv)}` ran instead of parsing"


def make_targets() -> set[str]:
    text = (ROOT / "Makefile").read_text()
    return set(re.findall(r"^([\w.-]+)\s*:(?!=)", text, flags=re.M))


def python_problem(argv: list[str]) -> str | None:
    """`python script.py args` or `python -m module args` (argv after the interpreter)."""
    if not argv:
        return None
    if argv[0] == "-m":
        if len(argv) < 2 or not (ROOT / argv[1].split(".")[0]).is_dir():
            return None  # a module from elsewhere (pytest, pip, venv)
        target = ROOT / (argv[1].replace(".", "/") + ".py")
        args = argv[2:]
    elif argv[0].endswith(".py"):
        target, args = ROOT / argv[0], argv[1:]
    else:
        return None
    if "$" in str(target):
        return None
    if not target.is_file():
        return f"`{target.relative_to(ROOT)}` does not exist"
    flags = [a.split("=")[0] for a in args if a.startswith("--")]
    if target.parent.name == "stages":
        from pipeline.cli import stage_parser

        known = {o for action in stage_parser("")._actions for o in action.option_strings}
    else:
        source = target.read_text()
        known = {f for f in flags if f'"{f}"' in source or f"'{f}'" in source}
    missing = [f for f in flags if f not in known]
    return f"`{target.relative_to(ROOT)}` has no option {missing[0]}" if missing else None


def page_problems(text: str, monkeypatch, capsys, base: Path = ROOT) -> list[str]:
    """Everything a page names that does not exist (an empty list when all of it does)."""
    spans, links, commands, yamls = split_page(text)
    problems = [p for block in yamls if (p := yaml_problem(block))]
    tracked, outputs = tracked_paths(), dvc_outputs()
    for command in commands:
        try:
            argv = shlex.split(command.replace("[", "").replace("]", ""))
        except ValueError:
            continue
        problems += _command_problems(argv, monkeypatch, capsys, full=True)
        skip = {i + 1 for i, a in enumerate(argv) if a in ("--out", "-o")}
        problems += [p for i, a in enumerate(argv) if i not in skip and looks_like_path(a)
                     and (p := path_problem(a, tracked, outputs))]
    for span in spans:
        try:
            argv = shlex.split(span)
        except ValueError:
            argv = span.split()
        if len(argv) > 1:
            problems += _command_problems(argv, monkeypatch, capsys, full=False)
        token = re.split(r"[:=\s]", span.strip())[0]
        if KEY.match(token):
            if problem := key_problem(token):
                problems.append(problem)
        elif looks_like_path(span) and (p := path_problem(span, tracked, outputs)):
            problems.append(p)
    for link in links:
        if "://" in link or link.startswith("mailto:"):
            continue
        target, _, anchor = link.partition("#")
        path = (base / target).resolve() if target else None
        if target:
            try:
                relative = path.relative_to(ROOT).as_posix()
            except ValueError:
                continue  # outside the repository
            if problem := path_problem(relative, tracked, outputs):
                problems.append(f"link {link}: {problem}")
                continue
        markdown = path if target else None
        if anchor and markdown is not None and markdown.suffix == ".md" and markdown.is_file():
            if anchor not in anchors(markdown):
                problems.append(f"link {link}: no heading with anchor #{anchor}")
    return problems


def _command_problems(argv: list[str], monkeypatch, capsys, full: bool) -> list[str]:
    problems = []
    for i, word in enumerate(argv):
        if word.endswith("adamimic") and i + 1 < len(argv) and not argv[i + 1].startswith("-"):
            if problem := cli_problem(argv[i + 1:], monkeypatch, capsys, full):
                problems.append(problem)
        elif word == "make" and i + 1 < len(argv):
            targets = [a for a in argv[i + 1:] if not a.startswith("-") and "=" not in a]
            problems += [f"`make {t}`: no such Makefile target" for t in targets[:1] if t not in make_targets()]
        elif re.fullmatch(r"(\S*/)?python(3(\.\d+)?)?", word):
            if problem := python_problem(argv[i + 1:]):
                problems.append(problem)
        elif word in ("-S", "--set") and i + 1 < len(argv):
            key = argv[i + 1].split("=")[0].strip("'\"")
            if problem := key_problem(key):
                problems.append(problem)
    return problems
