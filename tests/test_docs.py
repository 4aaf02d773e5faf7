"""The documentation is checked like code.

* Paths: every repository path that the docs (README.md, CONTRIBUTING.md, CHANGELOG.md,
  docs/**/*.md, examples/*/README.md), the scenario and config files, the code's docstrings and
  comments, and the `sep` --help texts cite exists. A repository path is a string that starts
  with one of the repository's top-level folders (`REPO_ROOTS`) followed by a slash, and is not
  the tail of a longer path or URL: `sep_plant/scenarios/plate.yaml`, `docs/reference/cli.md`,
  `bench/bench_scale.py`. So paths under `out/` or `/tmp`, `$(ros2 pkg prefix ...)/share/...`
  and user files (`model.fmu`, `wafer.yaml`) are examples, never checked. `*`, `<...>` and
  `{...}` make a pattern that must match at least one path. `NOT_IN_REPO` lists, with reasons,
  the cited paths that exist only after a build or later in this release.
* Links: every relative link and image of the Markdown files resolves, and every `#anchor` is a
  heading of its target.
* Completeness: every option of every `sep` subcommand (deprecated spellings too) appears in
  docs/reference/cli.md; every node parameter appears in docs/reference/parameters.md.
* Commands: every fenced block names its language; the shell blocks are cheap (run here, in a
  scratch folder), `<!-- long -->` (run by `python docs/check_commands.py --long`) or
  `<!-- no-run: REASON -->` (docs/check_commands.py says more).
* Shape: README.md opens with `make demo` and `make test` and has at most 250 lines; measurement
  diaries live in docs/benchmarks.md and CHANGELOG.md only; each shipped scenario's header has
  its own `sep design --scenario` command.
"""
from __future__ import annotations

import argparse
import glob
import importlib.util
import re
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent


def _load_check_commands():
    spec = importlib.util.spec_from_file_location("check_commands", REPO / "docs" / "check_commands.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module          # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


cc = _load_check_commands()

#: top-level folders of the repository: a cited path starting with one of them is a repository path
REPO_ROOTS = ("sep_plant", "sep_estimator", "sep_control", "examples", "docs", "bench", "tests", "ros_ws", ".ci")
PATH_RE = re.compile(r"(?<![\w./$~:@-])((?:" + "|".join(re.escape(r) for r in REPO_ROOTS)
                     + r")/[\w.*/<>{}-]*[\w*>}])")
#: cited paths that are not in the repository, on purpose: path (or folder prefix) -> why
NOT_IN_REPO = {
    "examples/fmu_rod/rod.fmu": "built from C source by `make fmu-rod` (ignored by git)",
    "ros_ws/install": "colcon's install space, made by `make build`",
    "ros_ws/build": "colcon's build folder, made by `make build`",
    "ros_ws/log": "colcon's logs, made by `make build`",
    "sep_plant/test": "optional ament_python per-package test folder (pytest.ini, Makefile)",
    "sep_estimator/test": "optional ament_python per-package test folder (pytest.ini, Makefile)",
    "sep_control/test": "optional ament_python per-package test folder (pytest.ini, Makefile)",
    "docs/reference/design-file.md": "the design-file reference, written by the integrator for this release",
    "docs/robustness.md": "model mismatch and disturbance estimation, written by the integrator for this release",
}
#: files whose text is scanned for cited paths (globs relative to the repository)
CITING_FILES = ("README.md", "CONTRIBUTING.md", "CHANGELOG.md", "docs/**/*.md", "examples/*/README.md",
                "sep_plant/scenarios/*.yaml", "examples/*/scenario.yaml", "*/config/*.yaml",
                "sep_plant/**/*.py", "sep_estimator/**/*.py", "sep_control/**/*.py", "bench/*.py", "bench/*.sh",
                "examples/**/*.py", "docs/*.py", "Makefile", ".ci/run", "requirements*.txt", "pytest.ini",
                "conftest.py", "ros_ws/*.sh")
MARKDOWN = ("README.md", "CONTRIBUTING.md", "CHANGELOG.md", "docs/**/*.md", "examples/*/README.md")


def _files(patterns) -> list[Path]:
    out: set[Path] = set()
    for pat in patterns:
        out.update(Path(p) for p in glob.glob(str(REPO / pat), recursive=True, include_hidden=True))
    return sorted(p for p in out if p.is_file() and "__pycache__" not in p.parts)


def cited_paths(text: str) -> list[tuple[int, str]]:
    """(line, path) of every repository path cited in `text` (see the module docstring)."""
    return [(n, m.group(1)) for n, line in enumerate(text.splitlines(), 1) for m in PATH_RE.finditer(line)]


def path_exists(path: str, root: Path = REPO) -> bool:
    """A cited path exists: as a file or folder, as a pattern matching one, or in NOT_IN_REPO."""
    path = path.rstrip("/")
    if any(path == p or path.startswith(p + "/") for p in NOT_IN_REPO):
        return True
    if any(c in path for c in "*<>{}"):
        pattern = re.sub(r"<[^>]*>|\{[^}]*\}", "*", path)
        return bool(glob.glob(str(root / pattern)))
    return (root / path).exists()


def test_path_rule_examples():
    """What counts as a repository path, on examples."""
    text = ("see sep_plant/scenarios/plate.yaml and `docs/reference/cli.md#exit-codes`; "
            "out/design.npz, /tmp/sep-0.6/bench/x.py, wafer.yaml, model.fmu, "
            "$(ros2 pkg prefix sep_plant)/share/sep_plant/config, https://example.org/docs/x, "
            "sep_plant.plants.blocks, INSTALL/sep_control/lib/x, sep_plant/scenarios/*.yaml.")
    assert [p for _, p in cited_paths(text)] == ["sep_plant/scenarios/plate.yaml", "docs/reference/cli.md",
                                                 "sep_plant/scenarios/*.yaml"]
    assert path_exists("sep_plant/scenarios/*.yaml") and path_exists("sep_plant/scenarios/plate.yaml")
    assert path_exists("examples/fmu_rod/rod.fmu")            # allowlisted: built by make fmu-rod
    assert not path_exists("sep_plant/scenarios/wafer.yaml")
    assert not path_exists("docs/no_such_page.md")


def test_cited_repository_paths_exist():
    """Docs, scenario and config files, docstrings and comments cite only paths that exist."""
    missing = []
    for f in _files(CITING_FILES):
        for line, path in cited_paths(f.read_text(encoding="utf-8", errors="replace")):
            if not path_exists(path):
                missing.append(f"{f.relative_to(REPO)}:{line}: {path}")
    assert not missing, "cited paths that do not exist:\n" + "\n".join(missing)


def _help_texts() -> dict[str, str]:
    from sep_control.cli.main import build_parser

    parser = build_parser()
    texts = {"sep": parser.format_help()}
    for name, sub in parser.get_default("_subparsers").items():
        texts[f"sep {name}"] = sub.format_help()
    return texts


def test_help_texts_cite_existing_paths():
    """The --help texts of `sep` and its subcommands cite only paths that exist."""
    missing = [f"{name}: {path}" for name, text in _help_texts().items()
               for _, path in cited_paths(text) if not path_exists(path)]
    assert not missing, "\n".join(missing)


# --------------------------------------------------------------------------------- links
def _strip_code(text: str) -> str:
    """The Markdown text without fenced blocks and inline code (links there are not links)."""
    text = re.sub(r"^ {0,3}(`{3,}|~{3,}).*?^ {0,3}\1\s*$", "", text, flags=re.S | re.M)
    return re.sub(r"`[^`\n]*`", "", text)


def github_slug(heading: str) -> str:
    """The anchor GitHub gives a heading: link text kept, punctuation dropped, spaces to '-'."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading).strip().lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    text = re.sub(r"^ {0,3}(`{3,}|~{3,}).*?^ {0,3}\1\s*$", "", path.read_text(encoding="utf-8"), flags=re.S | re.M)
    seen: dict[str, int] = {}
    out = set()
    for m in re.finditer(r"^#{1,6}\s+(.*?)\s*#*\s*$", text, flags=re.M):
        slug = github_slug(m.group(1))
        out.add(slug if slug not in seen else f"{slug}-{seen[slug]}")
        seen[slug] = seen.get(slug, 0) + 1
    return out


LINK_RE = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)|(?:src|href)=\"([^\"]+)\"")


def test_github_slug():
    assert github_slug("On a cluster: `--dask`") == "on-a-cluster---dask"
    assert github_slug("Scale (bench_scale.py)") == "scale-bench_scalepy"
    assert github_slug("`sep design`") == "sep-design"


def test_markdown_links_resolve():
    """Relative links and images point at files that exist, anchors at headings that exist."""
    bad = []
    for f in _files(MARKDOWN):
        for m in LINK_RE.finditer(_strip_code(f.read_text(encoding="utf-8"))):
            target = m.group(1) or m.group(2)
            if re.match(r"^[a-z][a-z0-9+.-]*:", target):          # http:, https:, mailto:
                continue
            file_part, _, anchor = target.partition("#")
            dest = (f.parent / file_part).resolve() if file_part else f
            rel = dest.relative_to(REPO).as_posix() if dest.is_relative_to(REPO) else str(dest)
            if not dest.exists():
                if not path_exists(rel):
                    bad.append(f"{f.relative_to(REPO)}: {target} (no such file)")
                continue
            if anchor and dest.suffix == ".md" and anchor not in anchors(dest):
                bad.append(f"{f.relative_to(REPO)}: {target} (no heading '{anchor}' in {rel})")
    assert not bad, "\n".join(bad)


# --------------------------------------------------------------------------- completeness
def _options(parser: argparse.ArgumentParser) -> set[str]:
    return {s for a in parser._actions for s in a.option_strings if s.startswith("--") and s != "--help"}


def test_every_sep_option_is_in_the_cli_reference():
    """Every option of every subcommand, deprecated spellings included, is in docs/reference/cli.md."""
    from sep_control.cli.main import build_parser
    from sep_control.ros.record_node import build_parser as record_parser

    doc = (REPO / "docs" / "reference" / "cli.md").read_text(encoding="utf-8")
    parser = build_parser()
    subs = {**parser.get_default("_subparsers"), "record": record_parser()}
    missing = [f"sep {name} {opt}" for name, sub in subs.items() for opt in sorted(_options(sub))
               if not re.search(r"(?<![\w-])" + re.escape(opt) + r"(?![\w-])", doc)]
    missing += [f"sep {name}" for name in subs if f"## `sep {name}`" not in doc]
    assert not missing, "not documented in docs/reference/cli.md:\n" + "\n".join(missing)


def test_every_node_parameter_is_in_the_parameters_reference():
    """Every parameter a node declares is in docs/reference/parameters.md."""
    doc = (REPO / "docs" / "reference" / "parameters.md").read_text(encoding="utf-8")
    declared = set()
    for f in _files(("sep_*/sep_*/ros/*.py",)):
        declared.update(re.findall(r"declare\(\s*node\s*,\s*'([a-z_0-9]+)'", f.read_text(encoding="utf-8")))
    assert {"scenario_file", "design_file", "controller", "field_precision"} <= declared
    missing = sorted(p for p in declared | {"use_sim_time"} if f"`{p}`" not in doc)
    assert not missing, f"parameters not in docs/reference/parameters.md: {missing}"


# ------------------------------------------------------------------------------ commands
def test_every_block_names_its_language_and_command_blocks_are_classified():
    """Each fenced block names its language; each shell block is fast, long or no-run (with a
    reason); markers sit right before a shell block (DocError otherwise)."""
    unnamed, kinds = [], {k: 0 for k in cc.KINDS}
    for f in cc.doc_files():
        for b in cc.parse_blocks(f):
            if not b.language:
                unnamed.append(b.where())
            if b.is_command:
                assert b.kind in cc.KINDS, b.where()
                assert b.kind != "no-run" or b.reason, b.where()
                kinds[b.kind] += 1
    assert not unnamed, f"code blocks without a language: {unnamed}"
    assert all(kinds.values()), f"every kind of block is used: {kinds}"


def test_block_parser(tmp_path):
    """The markers and their errors, on a small file."""
    md = tmp_path / "a.md"
    md.write_text("x\n\n```sh\nsep plants\n```\n\n<!-- long -->\n```sh\nmake demo\n```\n\n"
                  "<!-- no-run: needs a GPU -->\n```bash\nnvidia-smi\n```\n\n```text\nout\n```\n")
    blocks = cc.parse_blocks(md)
    assert [(b.language, b.kind, b.reason, b.line) for b in blocks] == [
        ("sh", "fast", "", 3), ("sh", "long", "", 8), ("bash", "no-run", "needs a GPU", 13), ("text", None, "", 17)]
    for bad in ("<!-- no-run -->\n```sh\nx\n```\n", "<!-- long -->\n\n```sh\nx\n```\n",
                "<!-- slow -->\n```sh\nx\n```\n", "<!-- long -->\n```text\nx\n```\n", "```sh\nx\n"):
        md.write_text(bad)
        with pytest.raises(cc.DocError):
            cc.parse_blocks(md)


def test_grep_selects_blocks_in_every_mode(tmp_path, monkeypatch, capsys):
    """--grep TEXT keeps the blocks that contain TEXT with --list and --fast (as with --long)."""
    md = tmp_path / "a.md"
    md.write_text("```sh\nsep plants\n```\n\n<!-- long -->\n```sh\nmake demo\nsep plants\n```\n\n"
                  "```sh\nsep --version\n```\n")
    assert [b.line for b in cc.command_blocks([md], grep="sep plants")] == [1, 6]
    assert [b.line for b in cc.command_blocks([md], "fast", "sep plants")] == [1]
    wanted = cc.command_blocks(cc.doc_files(), grep="sep plants")
    assert wanted and len(wanted) < len(cc.command_blocks(cc.doc_files()))
    assert cc.main(["--list", "--grep", "sep plants"]) == 0
    assert len(capsys.readouterr().out.splitlines()) == len(wanted)
    ran = []
    monkeypatch.setattr(cc, "run_block", lambda b, *a: ran.append(b) or argparse.Namespace(returncode=0))
    assert cc.main(["--fast", "--grep", "sep plants"]) == 0
    assert ran == [b for b in wanted if b.kind == "fast"] and ran


FAST_FILES = [f for f in cc.doc_files() if cc.command_blocks([f], "fast")]


@pytest.mark.slow
@pytest.mark.parametrize("doc", FAST_FILES, ids=[f.relative_to(REPO).as_posix() for f in FAST_FILES])
def test_fast_command_blocks_run(doc, tmp_path):
    """The unmarked shell blocks of each file run, in order, in a scratch folder."""
    failed = cc.run_fast([doc], tmp_path, log=lambda line: None)
    assert not failed, "\n\n".join(f"{b.where()} failed (exit {r.returncode}):\n{b.text}--- output:\n"
                                   f"{r.stdout[-4000:]}" for b, r in failed)


# --------------------------------------------------------------------------------- shape
def test_readme_is_short_and_opens_with_the_two_commands():
    text = (REPO / "README.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 250
    first = cc.parse_blocks(REPO / "README.md")[0]
    assert first.is_command and first.text.split()[:2] == ["make", "demo"] and "make test" in first.text


def test_measurement_diaries_only_in_benchmarks_and_changelog():
    """'Re-measured with sep 0.x' history lives in docs/benchmarks.md and CHANGELOG.md only."""
    allowed = {REPO / "docs" / "benchmarks.md", REPO / "CHANGELOG.md"}
    diaries = [f"{f.relative_to(REPO)}:{n}" for f in _files(MARKDOWN + ("sep_plant/scenarios/*.yaml",
                                                                     "examples/*/scenario.yaml"))
               if f not in allowed for n, line in enumerate(f.read_text(encoding="utf-8").splitlines(), 1)
               if re.search(r"re-measured with (the final )?sep \d", line, re.I)]
    assert not diaries, diaries


def test_scenario_headers_name_their_commands():
    """Each shipped scenario file says how to design it from itself."""
    for f in _files(("sep_plant/scenarios/*.yaml", "examples/*/scenario.yaml")):
        rel = f.relative_to(REPO).as_posix()
        header = f.read_text(encoding="utf-8").split("\nplant:", 1)[0]
        assert f"sep design --scenario {rel} " in header, rel
        assert "sep evaluate --design" in header, rel
