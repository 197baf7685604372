"""The documentation runs: every ```python block of README.md and docs/*.md (the blocks of one page
in order, in one namespace, as a reader pastes them), every script in examples/, and the results
tables equal what benchmarks/results_tables.py generates from docs/results/*.json.

Training calls in the docs (``.learn(N)``) run with a small budget, ``MARL_AMOD_DOCS_STEPS``
(default 512) agent-steps, so the suite stays fast; training examples take ``--steps``."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import results_tables  # benchmarks/ (pytest's pythonpath)

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
PYTHON_BLOCK = re.compile(r"^```python\n(.*?)^```", re.DOTALL | re.MULTILINE)
BUDGET = int(os.environ.get("MARL_AMOD_DOCS_STEPS", "512"))
EXAMPLE_ARGS = {
    "sb3_parameter_sharing.py": ["--steps", str(BUDGET), "--copies", "1", "--eval-episodes", "1"],
    "torchrl_mappo.py": ["--scenario", "synthetic", "--steps", "38", "--envs", "2", "--epochs", "1", "--eval-episodes", "1"],
    "benchmarl_task.py": ["--frames", "38", "--frames-per-batch", "38", "--envs", "2", "--eval-episodes", "1"],
    "agilerl_ippo.py": ["--steps", "38", "--envs", "2", "--eval-episodes", "1"],
    "tianshou_ppo.py": ["--steps", "38", "--envs", "2", "--eval-episodes", "1"],
}
# Examples for libraries outside the [dev] extra (each needs its own environment, see docs/ecosystem.md):
# they run where their library is installed and are skipped elsewhere.
EXAMPLE_NEEDS = {"benchmarl_task.py": "benchmarl", "agilerl_ippo.py": "agilerl", "tianshou_ppo.py": "tianshou"}



def _quick(code: str) -> str:
    return re.sub(r"\.learn\([\d_]+\)", f".learn({BUDGET})", code)


@pytest.mark.parametrize("page", [p for p in PAGES if PYTHON_BLOCK.search(p.read_text())], ids=lambda p: p.name)
def test_python_blocks_run(page: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from marl_amod.algos.registry import ALGOS
    from marl_amod.policies import POLICIES

    monkeypatch.chdir(tmp_path)  # anything a block writes stays out of the repository
    registries = [(r, dict(r)) for r in (ALGOS, POLICIES)]  # pages register toy policies and algorithms
    namespace: dict = {"__name__": "__docs__"}
    try:
        for i, block in enumerate(PYTHON_BLOCK.findall(page.read_text())):
            exec(compile(_quick(block), f"{page.name}[python block {i}]", "exec"), namespace)  # noqa: S102
    finally:
        for registry, saved in registries:
            registry.clear()
            registry.update(saved)


@pytest.mark.parametrize("script", sorted((ROOT / "examples").glob("*.py")), ids=lambda p: p.name)
def test_examples_run(script: Path, tmp_path: Path) -> None:
    if script.name in EXAMPLE_NEEDS:
        pytest.importorskip(EXAMPLE_NEEDS[script.name], reason=f"{script.name} runs in its own environment (docs/ecosystem.md)")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    out = subprocess.run([sys.executable, str(script), *EXAMPLE_ARGS.get(script.name, [])], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=300)  # fmt: skip
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.strip(), "an example should print what it shows"


def test_results_tables_match_the_committed_json() -> None:
    """No hand-edited numbers: README.md and docs/results.md tables are exactly the generator's output."""
    tables = results_tables.load()
    for doc in results_tables.DOCUMENTS:
        text = doc.read_text()
        assert results_tables.BLOCK.search(text), f"{doc.name} has no results block"
        assert results_tables.render(text, tables) == text, f"{doc.name}: run python benchmarks/results_tables.py"


def test_results_generator_scores_and_merges(tmp_path: Path) -> None:
    """ED scores 0 and MPC-Oracle 100; an evaluate record replaces a policy's numbers but keeps its notes."""
    doc = {"table": "x", "results": [
        {"policy": "equal-distribution", "metrics": {"profit": {"mean": 10.0, "std": 1.0}}},
        {"policy": "mpc-oracle", "metrics": {"profit": {"mean": 30.0, "std": 1.0}}},
        {"policy": "mine", "kind": "trained", "label": "my GNN", "training": "1 min", "metrics": {"profit": {"mean": 1.0}}},
    ]}  # fmt: skip
    assert [results_tables.score(p, doc) for p in (10.0, 30.0, 25.0)] == [0.0, 100.0, 75.0]
    (tmp_path / "x.json").write_text(__import__("json").dumps(doc))
    record = {"scenario": "x", "policy": "policies/mine.pt", "episodes": 3, "seed": 0,
              "metrics": {"profit": {"mean": 25.0, "std": 2.0}}}  # fmt: skip
    results_tables.merge([record], "x", tmp_path)
    merged = results_tables.load(tmp_path)["x"]["results"][2]
    assert merged["metrics"]["profit"]["mean"] == 25.0 and merged["label"] == "my GNN" and merged["training"] == "1 min"
    table = results_tables.table_markdown(results_tables.load(tmp_path)["x"], full=True)
    assert "| 75 |" in table and "**30 ± 1**" in table
    with pytest.raises(KeyError, match="nowhere"):
        results_tables.render("<!-- results:full nowhere -->\n<!-- /results -->", {})
    path = results_tables.figure("x", results_tables.load(tmp_path)["x"], tmp_path)
    assert path == tmp_path / "x.png" and path.read_bytes()[:4] == b"\x89PNG"
    assert results_tables.figure("y", {"results": doc["results"][2:]}, tmp_path) is None  # no anchors, no scores


def test_the_ranking_figure_puts_the_best_on_top_and_colours_by_kind() -> None:
    from marl_amod.plots import score_ranking_figure

    rows = [("ed", 0.0, 5.0, "baseline"), ("mine", 75.0, 10.0, "trained"), ("oracle", 100.0, 5.0, "baseline"), ("none", -40.0, 5.0, "baseline")]
    ax = score_ranking_figure(rows, "x").axes[0]
    assert [t.get_text() for t in ax.get_yticklabels()] == ["none", "ed", "mine", "oracle"]  # bottom to top
    assert [b.get_width() for b in ax.patches] == [-40.0, 0.0, 75.0, 100.0]
    colours = [b.get_facecolor() for b in ax.patches]
    assert colours[0] == colours[1] == colours[3] != colours[2]
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["baseline", "trained"]
    with pytest.raises(ValueError, match="at least one"):
        score_ranking_figure([])


def test_the_env_page_and_docstring_name_every_info_key() -> None:
    """docs/env.md's Infos row and the env's docstring list exactly the keys step() returns."""
    import marl_amod
    import marl_amod.env.parallel

    env = marl_amod.parallel_env("synthetic", horizon=3)
    _, infos = env.reset(seed=0)
    keys = set(infos["region_0"])
    row = next(line for line in (ROOT / "docs" / "env.md").read_text().splitlines() if line.startswith("| Infos |"))
    assert set(re.findall(r"`(\w+)`", row)) == keys
    doc = marl_amod.env.parallel.__doc__
    block = doc[doc.index("Infos (per agent") : doc.index("Global view")]
    assert set(re.findall(r"``(\w+)``", block)) == keys


# ------------------------------------------------------------------ names the pages mention
ALL_PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
COMMAND = re.compile(r"marl-amod ([a-z][\w-]*)((?:[ \t]+[^\s`|;)&]+)*)")


def stale_commands(text: str) -> list[str]:
    """``marl-amod SUB --flag ...`` mentions whose subcommand or flag the CLI does not have."""
    import typer.main

    from marl_amod.cli import app

    cli = typer.main.get_command(app)
    stale = []
    for m in COMMAND.finditer(text.replace("\\\n", " ")):  # shell line continuations join the command
        name, rest = m.group(1), m.group(2)
        command = cli.commands.get(name)
        if command is not None and hasattr(command, "commands"):  # a group: `plot wait-map`
            words = rest.split()
            command = command.commands.get(words[0]) if words else command
        if command is None:
            stale.append(f"unknown command in {m.group(0)[:80]!r}")
            continue
        flags = {opt for param in command.params for opt in getattr(param, "opts", ())} | {"--help"}
        stale += [f"{name}: no flag {flag}" for flag in re.findall(r"(?<![\w-])(--[a-z][\w-]*)", rest) if flag not in flags]
    return stale


def stale_names(text: str) -> list[str]:
    """Backticked ``marl_amod.a.b`` names that neither import nor resolve as attributes."""
    import importlib

    stale = []
    for name in sorted(set(re.findall(r"`[^`\n]*?\b(marl_amod(?:\.[A-Za-z_]\w*)+)", text))):
        parts = name.split(".")
        for i in range(len(parts), 0, -1):
            try:
                obj = importlib.import_module(".".join(parts[:i]))
            except ImportError:
                continue
            rest = parts[i:]
            while rest and hasattr(obj, rest[0]):
                obj = getattr(obj, rest.pop(0))
            if rest:
                stale.append(name)
            break
    return stale


def test_every_command_and_flag_the_pages_mention_exists() -> None:
    """A renamed flag or command leaves no page telling users to type it (README.md and docs/**)."""
    assert stale_commands("marl-amod evaluate --policy x --epochs 3 \\\n  --seeed 1; marl-amod plot wait-map --max-wait 3") == [
        "evaluate: no flag --epochs", "evaluate: no flag --seeed"]  # fmt: skip
    assert stale_commands("marl-amod evalute --help") != []
    for page in ALL_PAGES:
        assert stale_commands(page.read_text()) == [], page.relative_to(ROOT)


def test_every_marl_amod_name_the_guide_pages_mention_exists() -> None:
    """`marl_amod.x.y` in README.md and docs/** imports or resolves as an attribute."""
    assert stale_names("`marl_amod.env.render.record_episode` and `marl_amod.integrations.nothing_here`") == [
        "marl_amod.integrations.nothing_here"]  # fmt: skip
    for page in ALL_PAGES:
        assert stale_names(page.read_text()) == [], page.relative_to(ROOT)


# ------------------------------------------------------------------ scenario files the pages show
SCENARIO_BLOCK = re.compile(r"^```yaml\n# envs/(\w+)\.yaml[^\n]*\n(.*?)^```", re.DOTALL | re.MULTILINE)


def test_scenario_yaml_blocks_build_their_city(tmp_path: Path) -> None:
    """A scenario file a page shows (a ```yaml block headed ``# envs/<name>.yaml``) builds its city as
    written, under its own name (json cities only where MARL_AMOD_DATA is set)."""
    from conftest import has_data

    from marl_amod.scenario import load_city, load_spec

    blocks = [(name, body) for page in ALL_PAGES for name, body in SCENARIO_BLOCK.findall(page.read_text())]
    assert blocks, "docs/extending.md shows a scenario variant"
    for name, body in blocks:
        path = tmp_path / f"{name}.yaml"
        path.write_text(body)
        spec = load_spec(str(path))
        assert spec.name == name
        if spec.source != "json" or has_data():
            assert load_city(str(path)).name == name


def test_every_relative_link_and_image_of_the_guide_resolves() -> None:
    """A page, JSON or figure linked from README.md or docs/ exists (renamed or regenerated files
    leave no dead links); web links and in-page anchors are not followed."""
    link = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    targets = [(page, m.group(1)) for page in pages for m in link.finditer(page.read_text())]
    relative = [(page, t) for page, t in targets if not re.match(r"[a-z]+:", t) and not t.startswith("#")]
    assert len(relative) > 100  # the guide's cross-references, figures included
    dead = [f"{page.relative_to(ROOT)}: {t}" for page, t in relative if not (page.parent / t.split("#")[0]).exists()]
    assert not dead, dead


SCRIPT = re.compile(r"python (?:-m )?((?:benchmarks|examples)/[\w/]+\.py)((?:[ \t]+[^\s`|;)&]+)*)")


def stale_script_mentions(text: str) -> list[str]:
    """``python benchmarks/x.py --flag`` (or examples/) mentions whose script is gone or has no such
    flag (read from the script's ``add_argument`` calls, without running it)."""
    stale = []
    for m in SCRIPT.finditer(text.replace("\\\n", " ")):
        script, rest = ROOT / m.group(1), m.group(2)
        if not script.is_file():
            stale.append(f"no script {m.group(1)}")
            continue
        source = script.read_text()
        stale += [f"{m.group(1)}: no flag {flag}" for flag in re.findall(r"(?<![\w-])(--[a-z][\w-]*)", rest)
                  if flag != "--help" and f'"{flag}"' not in source]  # fmt: skip
    return stale


def missing_configs(text: str) -> list[str]:
    """``--config configs/...yaml`` paths a page tells users to train or compare with that are not in the
    repository (one the page writes out itself, headed ``# configs/....yaml``, is an example to copy)."""
    return sorted({p for p in re.findall(r"--config (configs/[\w./-]+\.yaml)", text) if not (ROOT / p).is_file() and f"# {p}" not in text})


def test_every_script_flag_and_config_the_pages_mention_exists() -> None:
    assert stale_script_mentions("python benchmarks/results_tables.py --check --chekc; python benchmarks/nope.py") == [
        "benchmarks/results_tables.py: no flag --chekc", "no script benchmarks/nope.py"]  # fmt: skip
    assert missing_configs("marl-amod train --config configs/a2c/synthetic.yaml --config configs/a2c/atlantis.yaml") == [
        "configs/a2c/atlantis.yaml"]  # fmt: skip
    assert missing_configs("# configs/mine/x.yaml\nalgo: a2c\n... marl-amod train --config configs/mine/x.yaml") == []
    for page in ALL_PAGES:
        text = page.read_text()
        assert stale_script_mentions(text) == [] and missing_configs(text) == [], page.relative_to(ROOT)
