#!/usr/bin/env python3
"""Run the shell commands of the documentation's code blocks.

The documentation is `README.md`, `CONTRIBUTING.md`, `CHANGELOG.md` and `docs/**/*.md`. Every
fenced code block there names its language; a block in a shell language (sh, bash, shell,
console) holds commands, run from the repository root, and is one of three kinds, set by an HTML
comment on the line just before its opening fence:

* no comment: cheap. `tests/test_docs.py` runs it on every `make test`, in a scratch folder that
  links the repository's top-level entries, with `sep` and `python` running this checkout
  (`--fast` here does the same);
* ``<!-- long -->``: takes long or needs the built workspace (`make demo`, 1000-run evaluations,
  benchmarks). `--long` runs these in a fresh clone after `make build`, with the clone's
  `.venv/bin` first on PATH: what a maintainer runs before a release;
* ``<!-- no-run: REASON -->``: needs what neither a developer machine nor CI has (several
  machines, a GPU, a native ROS 2 install from apt); never run, the reason says why.

The blocks of one file run in order in one folder, so a later block may use what an earlier one
wrote (under `out/`). Commands write only under `out/` or `/tmp`.

    python docs/check_commands.py --list                     # every command block and its kind
    python docs/check_commands.py --fast                     # the cheap blocks, in a scratch folder
    python docs/check_commands.py --long                     # fresh clone, make build, the long blocks
    python docs/check_commands.py --long --only README.md docs/reference/cli.md --grep "sep demo"
    python docs/check_commands.py --fast --grep "sep analyze"      # --grep selects in every mode

Exit status 1 when a block fails (its output is printed), 2 for bad arguments. Standard library
only.
"""
from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
#: languages whose blocks are commands
SHELL_LANGUAGES = ("sh", "bash", "shell", "console")
KINDS = ("fast", "long", "no-run")
_FENCE = re.compile(r"^(?P<indent> {0,3})(?P<fence>`{3,}|~{3,})(?P<info>.*)$")
_MARKER = re.compile(r"^\s*<!--\s*(?P<kind>long|no-run)\s*(?::\s*(?P<reason>.*?))?\s*-->\s*$")
_ANY_MARKER = re.compile(r"^\s*<!--\s*(long|no-run|fast|skip|slow)\b")
#: entries of the repository root never linked into a scratch folder
_NOT_LINKED = {".git", ".venv", "out", ".pytest_cache", "__pycache__"}
#: seconds one block may take in --fast (tests) and --long
FAST_TIMEOUT_S = 600
LONG_TIMEOUT_S = 6 * 3600


@dataclass(frozen=True)
class Block:
    """One fenced code block of a Markdown file."""

    path: Path          # the Markdown file
    line: int           # 1-based line of the opening fence
    language: str       # first word of the info string ('' when none)
    text: str           # the block's content
    kind: str | None    # commands: 'fast', 'long' or 'no-run'; None for other languages
    reason: str = ""    # why a 'no-run' block is not run

    @property
    def is_command(self) -> bool:
        return self.language in SHELL_LANGUAGES

    def where(self, root: Path = REPO) -> str:
        try:
            return f"{self.path.relative_to(root)}:{self.line}"
        except ValueError:
            return f"{self.path}:{self.line}"


class DocError(ValueError):
    """A Markdown file breaks the rules above (the message names the file and line)."""


def doc_files(root: Path = REPO) -> list[Path]:
    """The documentation whose blocks are checked: README, CONTRIBUTING, CHANGELOG, docs/**."""
    top = [root / n for n in ("README.md", "CONTRIBUTING.md", "CHANGELOG.md") if (root / n).is_file()]
    return top + sorted((root / "docs").rglob("*.md"))


def parse_blocks(path: Path) -> list[Block]:
    """Every fenced block of `path` with its kind; DocError for an unclosed fence, a marker that
    is not right before a command block, or a 'no-run' without a reason."""
    lines = path.read_text(encoding="utf-8").splitlines()
    blocks: list[Block] = []
    i = 0
    while i < len(lines):
        m = _FENCE.match(lines[i])
        if not m:
            if _ANY_MARKER.match(lines[i]):
                nxt = lines[i + 1] if i + 1 < len(lines) else ""
                fence = _FENCE.match(nxt)
                if not _MARKER.match(lines[i]):
                    raise DocError(f"{path}:{i + 1}: unknown block marker {lines[i].strip()!r} "
                                   "(known: <!-- long -->, <!-- no-run: REASON -->)")
                if not fence or fence.group("info").strip().split(" ")[0] not in SHELL_LANGUAGES:
                    raise DocError(f"{path}:{i + 1}: a block marker must be on the line right before "
                                   "the opening fence of a shell block")
            i += 1
            continue
        fence, start = m.group("fence"), i
        language = (m.group("info").strip().split() or [""])[0]
        body: list[str] = []
        i += 1
        while i < len(lines) and not (lines[i].strip().startswith(fence[0] * len(fence))
                                      and set(lines[i].strip()) == {fence[0]}):
            body.append(lines[i])
            i += 1
        if i >= len(lines):
            raise DocError(f"{path}:{start + 1}: code block not closed")
        kind, reason = None, ""
        if language in SHELL_LANGUAGES:
            marker = _MARKER.match(lines[start - 1]) if start > 0 else None
            kind = marker.group("kind") if marker else "fast"
            reason = (marker.group("reason") or "") if marker else ""
            if kind == "no-run" and not reason:
                raise DocError(f"{path}:{start}: <!-- no-run: REASON --> needs a reason")
        blocks.append(Block(path, start + 1, language, "\n".join(body) + "\n", kind, reason))
        i += 1
    return blocks


def command_blocks(paths: list[Path], kind: str | None = None, grep: str | None = None) -> list[Block]:
    """The shell blocks of `paths` (of one kind, and containing `grep`, when given), in file order."""
    return [b for p in paths for b in parse_blocks(p)
            if b.is_command and (kind is None or b.kind == kind) and (grep is None or grep in b.text)]


# ----------------------------------------------------------------------------- running
def scratch_folder(dest: Path, root: Path = REPO) -> dict[str, str]:
    """Make `dest` a working folder for the fast blocks: symlinks to the repository's top-level
    entries (so `sep_plant/scenarios/plate.yaml` resolves; outputs go to dest/out), and a bin/
    with `sep`, `python` and `python3` running this checkout's packages with this interpreter.
    Returns the environment to run the blocks with."""
    dest.mkdir(parents=True, exist_ok=True)
    for entry in root.iterdir():
        if entry.name not in _NOT_LINKED and not (dest / entry.name).exists():
            (dest / entry.name).symlink_to(entry)
    bin_dir = dest / ".bin"
    bin_dir.mkdir(exist_ok=True)
    shims = {"sep": f'exec "{sys.executable}" -m sep_control.cli.main "$@"',
             "python": f'exec "{sys.executable}" "$@"', "python3": f'exec "{sys.executable}" "$@"'}
    for name, line in shims.items():
        shim = bin_dir / name
        shim.write_text(f"#!/bin/sh\n{line}\n")
        shim.chmod(0o755)
    env = dict(os.environ)
    pkgs = [str(root / p) for p in ("sep_plant", "sep_estimator", "sep_control", "examples/burgers")]
    env["PYTHONPATH"] = os.pathsep.join(pkgs + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    env["PATH"] = os.pathsep.join([str(bin_dir), env.get("PATH", "")])
    env.setdefault("MPLBACKEND", "Agg")
    env["OPENBLAS_NUM_THREADS"] = "1"
    return env


def run_block(block: Block, cwd: Path, env: dict[str, str], timeout: float) -> subprocess.CompletedProcess:
    """Run a block's commands with bash (-e -u -o pipefail) in `cwd`; stdout and stderr together."""
    try:
        return subprocess.run(["bash", "-euo", "pipefail", "-c", block.text], cwd=cwd, env=env,
                              stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              text=True, timeout=timeout)
    except subprocess.TimeoutExpired as exc:
        out = exc.stdout.decode() if isinstance(exc.stdout, bytes) else (exc.stdout or "")
        return subprocess.CompletedProcess(exc.cmd, 124, out + f"\n(timed out after {timeout:g} s)")


def run_blocks(blocks: list[Block], cwd: Path, env: dict[str, str], timeout: float,
               log=print) -> list[tuple[Block, subprocess.CompletedProcess]]:
    """Run `blocks` in order; the failed ones with their results."""
    failed = []
    for b in blocks:
        t0 = time.perf_counter()
        res = run_block(b, cwd, env, timeout)
        log(f"{'ok  ' if res.returncode == 0 else 'FAIL'} {b.where()} ({b.kind}, {time.perf_counter() - t0:.1f} s)")
        if res.returncode != 0:
            failed.append((b, res))
    return failed


def run_fast(paths: list[Path], workdir: Path, grep: str | None = None,
             log=print) -> list[tuple[Block, subprocess.CompletedProcess]]:
    """The fast blocks of each file (those containing `grep` when given) in a scratch folder of
    its own under `workdir`."""
    failed = []
    for p in paths:
        blocks = command_blocks([p], "fast", grep)
        if blocks:
            dest = workdir / p.relative_to(REPO).as_posix().replace("/", "_")
            failed += run_blocks(blocks, dest, scratch_folder(dest), FAST_TIMEOUT_S, log)
    return failed


def run_long(paths: list[Path], workdir: Path, grep: str | None = None,
             log=print) -> list[tuple[Block, subprocess.CompletedProcess]]:
    """A fresh clone of the committed tree, `make build` there, then the long blocks (those
    containing `grep` when given; all files in one folder, the clone's root, in document order)."""
    clone = workdir / "clone"
    subprocess.run(["git", "clone", "--quiet", str(REPO), str(clone)], check=True)
    env = dict(os.environ)
    env["PATH"] = os.pathsep.join([str(clone / ".venv" / "bin"), env.get("PATH", "")])
    env.setdefault("MPLBACKEND", "Agg")
    log(f"make build in {clone} ...")
    build = subprocess.run(["make", "build"], cwd=clone, env=env, stdout=subprocess.PIPE,
                           stderr=subprocess.STDOUT, text=True)
    if build.returncode != 0:
        raise SystemExit(f"make build failed in the clone:\n{build.stdout[-4000:]}")
    blocks = command_blocks([clone / p.relative_to(REPO) for p in paths], "long", grep)
    return run_blocks(blocks, clone, env, LONG_TIMEOUT_S, log)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    what = ap.add_mutually_exclusive_group(required=True)
    what.add_argument("--list", action="store_true", help="list every command block and its kind")
    what.add_argument("--fast", action="store_true", help="run the cheap blocks here (what the tests run)")
    what.add_argument("--long", action="store_true", help="run the long blocks in a fresh clone")
    ap.add_argument("--only", nargs="+", metavar="FILE", help="only these Markdown files (repository paths)")
    ap.add_argument("--grep", metavar="TEXT", help="only the blocks that contain TEXT (with --list, --fast or --long)")
    ap.add_argument("--keep", action="store_true", help="keep the scratch folder (its path is printed)")
    args = ap.parse_args(argv)
    paths = doc_files()
    if args.only:
        wanted = {(REPO / f).resolve() for f in args.only}
        missing = [f for f in args.only if not (REPO / f).is_file()]
        if missing:
            ap.error(f"no such file: {', '.join(missing)}")
        paths = [p for p in paths if p.resolve() in wanted]
    try:
        blocks = command_blocks(paths, grep=args.grep)
    except DocError as exc:
        print(f"check_commands: error: {exc}", file=sys.stderr)
        return 2
    if args.list:
        for b in blocks:
            first = b.text.strip().splitlines()[0] if b.text.strip() else ""
            print(f"{b.kind:7s} {b.where():40s} {first[:70]}" + (f"   [{b.reason}]" if b.reason else ""))
        return 0
    workdir = Path(tempfile.mkdtemp(prefix="sep-doc-commands-"))
    try:
        if args.fast:
            failed = run_fast(paths, workdir, args.grep)
        else:
            failed = run_long(paths, workdir, args.grep)
    finally:
        if args.keep:
            print(f"scratch folder kept: {workdir}")
        else:
            shutil.rmtree(workdir, ignore_errors=True)
    for b, res in failed:
        print(f"\n--- {b.where()} failed (exit {res.returncode}):\n{b.text}--- output:\n{res.stdout[-6000:]}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
