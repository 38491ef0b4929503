"""``tvopt-codegen tune``: the search on compiled sweeps, its files, its resume, its refusals.

Small tunes of the bundled PVTOL (a 4 s horizon, a handful of samples and candidates) on
the in-process worker: what a tune writes, that the same command writes the same tuned
spec, that a tune killed by SIGTERM and resumed ends where the uninterrupted one did, and
that bad requirements are one line with nothing written.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest

from tvopt_codegen.errors import EXIT_BAD_SPEC, EXIT_INTERRUPTED, EXIT_TERMINATED
from tvopt_codegen.maths import hurwitz
from tvopt_codegen.sweep.program import transient_constant
from tvopt_codegen.tune.requirements import requirements_from
from tvopt_codegen.tune.search import cma_optimizer
from tvopt_codegen.tune.session import Evaluation, Search
from tvopt_codegen.tune.space import Candidate, space_for

from .conftest import ROOT, run_main, shared

pytest.importorskip("cma")
pytest.importorskip("pyarrow")

EXAMPLES = ROOT / "tvopt_codegen" / "examples"

#: A small tune of PVTOL: 10% mass and inertia mismatch, noise, 100 Hz, saturated inputs.
PVTOL = (
    "pvtol",
    "--samples", "12",
    "--evaluations", "24",
    "--population", "6",
    "--seed", "3",
    "--t-final", "4",
    "--points", "41",
    "--plant-param", "m=normal(1, 0.1)",
    "--plant-param", "J=normal(1, 0.1)",
    "--measurement-noise", "0.001",
    "--sample-time", "0.01",
    "--saturation", "thrust=0:20",
    "--saturation", "torque=5",
    "--check-samples", "40",
    "--workers", "1",
    "--progress", "never",
)  # fmt: skip

TUNED = "pvtol_tuned.toml"

#: A resume's own options: on the in-process worker, as the tune it resumes. Without
#: --workers it would start a local cluster of two cold interpreters for these few
#: samples (what a cluster gives: test_on_a_dask_cluster_the_search_is_the_same).
RESUME = ("--workers", "1", "--progress", "never")


@pytest.fixture(scope="module")
def reference() -> Path:
    """One uninterrupted small tune of PVTOL, tuned once per run for every worker."""

    def tune_once(folder: Path) -> None:
        ran = run_main("tune", *PVTOL, "--out", str(folder / "out"))
        assert ran.returncode == 0, ran.stderr

    return shared("tune-command-reference", tune_once) / "out"


def test_a_tune_writes_a_tuned_spec_that_does_better_on_fresh_samples(reference: Path) -> None:
    names = {p.name for p in reference.iterdir() if not p.name.startswith(".")}
    assert {
        "pvtol.toml",
        TUNED,
        "tune.json",
        "tune.md",
        "evaluations.csv",
        "tune_tradeoff.png",
        "tune_tradeoff.svg",
    } <= names
    record = json.loads((reference / "tune.json").read_text())
    assert record["state"] == "complete"
    evaluations = record["evaluations"]
    assert len(evaluations) == 25  # the spec's gains, then 24 candidates
    assert [e["index"] for e in evaluations] == list(range(25))
    chosen = evaluations[record["best"]]
    # The tuned spec is the bundled one with the chosen poles: the same law otherwise.
    original = tomllib.loads((EXAMPLES / "pvtol.toml").read_text())
    tuned = tomllib.loads((reference / TUNED).read_text())
    assert tuned["error_dynamics"]["poles"] == [re for re, _ in chosen["poles"]]
    tuned["error_dynamics"] = original["error_dynamics"]
    assert tuned == original
    assert (reference / "pvtol.toml").read_bytes() == (EXAMPLES / "pvtol.toml").read_bytes()
    # Better than the spec's gains on its own samples, and on the fresh ones too.
    fresh = record["fresh"]
    assert fresh["samples"] == 40 and fresh["seed"] == 4
    assert chosen["objective"] < evaluations[0]["objective"]
    assert fresh["tuned"]["objective"] < fresh["original"]["objective"]
    assert fresh["tuned"]["failure_bound"] <= fresh["original"]["failure_bound"]
    text = (reference / "tune.md").read_text()
    assert "## On 40 fresh samples (seed 4)" in text
    assert "failure_bound <= " in text and "the spec's gains' own bound" in text
    header = (reference / TUNED).read_text().splitlines()[:3]
    assert header[0].startswith("# Tuned by tvopt-codegen tune (cma, 24 candidates")
    rows = (reference / "evaluations.csv").read_text().splitlines()
    assert len(rows) == 26 and rows[0].startswith("index,generation,position,pole0_re")


def test_the_same_command_writes_the_same_tuned_spec(reference: Path, tmp_path: Path) -> None:
    # Every candidate's transient constant computed again too, as in another process
    # (the sweep's cache and hurwitz's own).
    transient_constant.cache_clear()
    hurwitz._transient_constant.cache_clear()
    ran = run_main("tune", *PVTOL, "--out", str(tmp_path / "again"))
    assert ran.returncode == 0, ran.stderr
    for name in (TUNED, "evaluations.csv", "tune.md", "tune.json"):
        assert (tmp_path / "again" / name).read_bytes() == (reference / name).read_bytes(), name


def test_a_candidates_transient_constant_is_computed_once_per_process() -> None:
    """A tune's candidate met again (its fresh check, another tune of the same seed) gets
    the transient constant already computed: the same float as hurwitz's."""
    values = hurwitz.coefficients_from_poles([-0.5, -3.0, -6.0, -9.0])
    alpha, _ = hurwitz.certified_rate(values)
    transient_constant.cache_clear()
    first = transient_constant(tuple(values), alpha)
    assert first == hurwitz.transient_constant(values, alpha) and first > 10
    assert transient_constant(tuple(values), alpha) == first
    assert transient_constant.cache_info().hits == 1


@pytest.mark.parametrize(
    ("number", "code", "word"),
    [
        (signal.SIGTERM, EXIT_TERMINATED, "terminated"),
        (signal.SIGINT, EXIT_INTERRUPTED, "interrupted"),
    ],
)
def test_a_stopped_tune_keeps_the_best_and_resumes_to_the_uninterrupted_end(
    reference: Path, tmp_path: Path, number: int, code: int, word: str
) -> None:
    """SIGTERM (a batch system's wall time) and Ctrl-C (SIGINT to the terminal's group)."""
    out = tmp_path / "out"
    command = [sys.executable, "-m", "tvopt_codegen", "tune", *PVTOL, "--out", str(out)]
    process = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True
    )
    deadline = time.monotonic() + 120
    # Wait for the spec's gains and the first generation to be recorded (of four).
    while time.monotonic() < deadline:
        try:
            done = len(json.loads((out / "tune.json").read_text())["evaluations"])
        except (OSError, ValueError, KeyError):
            done = 0
        if done >= 7:
            break
        time.sleep(0.02)
    os.killpg(process.pid, number)
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == code, stderr
    last = stderr.strip().splitlines()[-1]
    assert f"{word} after" in last and "kept the best so far" in last and "--resume" in last
    record = json.loads((out / "tune.json").read_text())
    assert record["state"] == "interrupted"
    assert 7 <= len(record["evaluations"]) < 25
    assert "Interrupted" in (out / TUNED).read_text()
    resumed = run_main("tune", "--resume", str(out), *RESUME)
    assert resumed.returncode == 0, resumed.stderr
    for name in (TUNED, "evaluations.csv", "tune.md"):
        assert (out / name).read_bytes() == (reference / name).read_bytes(), name
    again = run_main("tune", "--resume", str(out))
    assert again.returncode == 0 and "nothing to resume" in again.stderr


def test_a_signal_in_the_fresh_check_keeps_the_best_and_resumes(
    reference: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The search done, the check on fresh samples cut by SIGTERM: the best is kept, and a
    resume replays the whole search without a sweep, checks, and ends as the reference."""
    from tvopt_codegen.errors import Terminated
    from tvopt_codegen.tune import evaluate

    def terminated(*args: object) -> None:
        raise Terminated

    monkeypatch.setattr(evaluate, "fresh_check", terminated)
    out = tmp_path / "out"
    ran = run_main("tune", *PVTOL, "--out", str(out))
    assert ran.returncode == EXIT_TERMINATED, ran.stderr
    assert "kept the best so far" in ran.stderr.strip().splitlines()[-1]
    record = json.loads((out / "tune.json").read_text())
    assert record["state"] == "interrupted" and len(record["evaluations"]) == 25
    assert "Interrupted" in (out / TUNED).read_text()
    monkeypatch.undo()
    resumed = run_main("tune", "--resume", str(out), *RESUME)
    assert resumed.returncode == 0, resumed.stderr
    for name in (TUNED, "evaluations.csv", "tune.md"):
        assert (out / name).read_bytes() == (reference / name).read_bytes(), name


def test_requirements_no_candidate_meets_are_said_not_hidden(tmp_path: Path) -> None:
    out = tmp_path / "out"
    args = ("--constraint", "max(peak_thrust) <= 0.01", "--evaluations", "6")
    # A thrust of 0.01 holds no PVTOL up, whatever the samples: 4 of each show it.
    args += ("--samples", "4", "--check-samples", "4")
    ran = run_main("tune", *PVTOL, *args, "--out", str(out))
    assert ran.returncode == 0, ran.stderr
    assert "warning: no candidate met every requirement" in ran.stderr
    assert "No candidate met every requirement" in (out / TUNED).read_text()
    assert "**No candidate met every requirement**" in (out / "tune.md").read_text()


def test_a_choice_on_the_edge_of_the_box_is_said(tmp_path: Path) -> None:
    """Poles confined to [2.6, 3] rad/s, where faster is better: the best is on the edge."""
    out = tmp_path / "out"
    ran = run_main("tune", *PVTOL, "--pole-range", "2.6:3", "--out", str(out))
    assert ran.returncode == 0, ran.stderr
    text = (out / "tune.md").read_text()
    assert "sit on the edge of the searched box (a pole of magnitude 3" in text


def test_on_a_dask_cluster_the_search_is_the_same(reference: Path, tmp_path: Path) -> None:
    """Two worker processes: each generation's chunks spread over them, the loop's sources
    scattered once, every candidate's rows the in-process worker's, so the same search."""
    pytest.importorskip("distributed")
    args = list(PVTOL)
    args[args.index("--workers") + 1] = "2"
    ran = run_main("tune", *args, "--out", str(tmp_path / "out"))
    assert ran.returncode == 0, ran.stderr
    for name in (TUNED, "evaluations.csv", "tune.md"):
        assert (tmp_path / "out" / name).read_bytes() == (reference / name).read_bytes(), name


def test_a_record_cut_mid_generation_out_of_order_resumes(reference: Path, tmp_path: Path) -> None:
    """A cluster finishes a generation's candidates out of order: a record cut there has a
    gap in its last generation (candidates 1, 3 and 4 of generation 2 missing here), and
    the resume sweeps just those and ends as the uninterrupted tune."""
    import shutil

    out = tmp_path / "out"
    shutil.copytree(reference, out)
    record = json.loads((out / "tune.json").read_text())
    kept = [
        e for e in record["evaluations"]
        if e["generation"] < 2 or (e["generation"] == 2 and e["position"] in (0, 2, 5))
    ]  # fmt: skip
    assert [e["index"] for e in kept][-3:] == [13, 15, 18]
    for key in ("best", "fresh"):
        del record[key]
    record |= {"evaluations": kept, "state": "interrupted"}
    (out / "tune.json").write_text(json.dumps(record, indent=1) + "\n")
    ran = run_main("tune", "--resume", str(out), *RESUME)
    assert ran.returncode == 0, ran.stderr
    for name in (TUNED, "evaluations.csv", "tune.md"):
        assert (out / name).read_bytes() == (reference / name).read_bytes(), name


def test_a_resume_takes_no_new_options(reference: Path) -> None:
    ran = run_main("tune", "--resume", str(reference), "--samples", "5")
    assert ran.returncode == EXIT_BAD_SPEC
    assert "--samples: not with --resume" in ran.stderr


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (("--objective", "p42(final_error)"), "--objective"),
        (("--objective", "p95(happiness)"), "--objective"),
        (("--constraint", "failure_bound <= 0.001"), "--constraint"),
        (("--constraint", "mean(saturation) <= 2"), "--constraint"),
        (("--pole-range", "5:1"), "--pole-range"),
        (("--min-damping", "2"), "--min-damping"),
        (("--complex-pairs", "3"), "--complex-pairs"),
        (("--bandwidth-range", "1:10"), "--bandwidth-range"),
        (("--after", "9"), "--after"),
        (("--evaluations", "0"), "--evaluations"),
        (("--check-seed", "3"), "--check-seed"),
    ],
)
def test_bad_requirements_are_one_line_and_nothing_is_written(
    tmp_path: Path, extra: tuple[str, ...], message: str
) -> None:
    out = tmp_path / "out"
    ran = run_main("tune", *PVTOL, *extra, "--out", str(out))
    assert ran.returncode == EXIT_BAD_SPEC, ran.stderr
    lines = ran.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], ran.stderr
    assert not out.exists()


def test_an_earlier_tune_is_not_replaced_without_force(reference: Path, tmp_path: Path) -> None:
    before = {p.name: p.read_bytes() for p in reference.iterdir() if p.is_file()}
    ran = run_main("tune", *PVTOL, "--out", str(reference))
    assert ran.returncode == 4 and "already holds a tune" in ran.stderr
    assert {p.name: p.read_bytes() for p in reference.iterdir() if p.is_file()} == before


def test_the_spec_tune_table_sets_the_requirements_and_the_observer_is_tuned(
    tmp_path: Path,
) -> None:
    """robust_pvtol: integral action (5 poles, one real for the integral), an observer whose
    bandwidth is searched, and the requirements from the spec's [tune] table."""
    text = (ROOT / "tests" / "specs" / "robust_pvtol.toml").read_text()
    text += (
        '\n[tune]\nobjective = "mean(integrated_error)"\nafter = 1.0\n'
        "pole_range = [0.5, 8.0]\nbandwidth_range = [5.0, 60.0]\n"
    )
    spec = tmp_path / "robust.toml"
    spec.write_text(text)
    args = [a if a != "pvtol" else str(spec) for a in PVTOL]
    ran = run_main("tune", *args, "--evaluations", "6", "--out", str(tmp_path / "out"))
    assert ran.returncode == 0, ran.stderr
    record = json.loads((tmp_path / "out" / "tune.json").read_text())
    markdown = (tmp_path / "out" / "tune.md").read_text()
    assert "minimise mean(integrated_error)" in markdown
    assert "one of them the integral" in markdown and "[5, 60] rad/s" in markdown
    bandwidths = {e["bandwidth"] for e in record["evaluations"]}
    assert len(bandwidths) > 1 and all(5.0 <= b <= 60.0 for b in bandwidths - {20.0})
    chosen = record["evaluations"][record["best"]]
    tuned = tomllib.loads((tmp_path / "out" / "robust_pvtol_tuned.toml").read_text())
    assert tuned["robust"]["observer"]["bandwidth"] == chosen["bandwidth"]
    assert len(tuned["error_dynamics"]["poles"]) == 5
    assert tuned["tune"]["objective"] == "mean(integrated_error)"


@pytest.mark.parametrize(
    ("method", "words"), [("random", "uniform random points"), ("tpe", "optuna's TPE")]
)
def test_the_other_searches_run_the_same_budget(tmp_path: Path, method: str, words: str) -> None:
    if method == "tpe":
        pytest.importorskip("optuna")
    # The budget and the method's words do not depend on the samples: 4 of each.
    fewer = ("--samples", "4", "--check-samples", "4")
    ran = run_main("tune", *PVTOL, *fewer, "--method", method, "--out", str(tmp_path / "out"))
    assert ran.returncode == 0, ran.stderr
    record = json.loads((tmp_path / "out" / "tune.json").read_text())
    assert len(record["evaluations"]) == 25
    assert [e["generation"] for e in record["evaluations"][1:]] == [
        g for g in range(4) for _ in range(6)
    ]
    assert words in (tmp_path / "out" / "tune.md").read_text()
    # TPE's first trial is the spec's own gains (rounded), as CMA-ES starts there.
    if method == "tpe":
        assert record["evaluations"][1]["poles"] == record["evaluations"][0]["poles"]


def _fake_rows(candidate: Candidate) -> list[dict[str, object]]:
    """Four samples whose errors are a smooth function of the gains (no sweep)."""
    error = float(sum((p.real + 2.0) ** 2 for p in candidate.poles)) + 0.1
    return [
        {"status": "ok", "final_error": error / (k + 1), "time_saturated": 0.0,
         "max_abs_u": 1.0, "sample": k}
        for k in range(4)
    ]  # fmt: skip


def _search(seed: int, history: list[Evaluation] | None = None) -> Search:
    space = space_for((-1 + 0j, -3 + 0j), None, integral=False)
    requirements = requirements_from(
        None, "test", None, (), None, samples=4, t_final=1.0, inputs=("u",)
    )
    start = space.encode(ORIGINAL_GAINS)
    return Search(
        space, requirements, cma_optimizer(start, seed, 5), 20, 1.0, ("u",), history or []
    )


ORIGINAL_GAINS = Candidate(poles=(-1 + 0j, -3 + 0j), bandwidth=None)


class _StopError(Exception):
    """The fake sweep's Ctrl-C."""


def _sweeper(stop_after: int | None, swept: list[Candidate]):  # noqa: ANN202
    def sweep(candidates: list[Candidate], done) -> None:  # noqa: ANN001
        # Complete them out of order, as a cluster does: the last first.
        for j in reversed(range(len(candidates))):
            if stop_after is not None and len(swept) >= stop_after:
                raise _StopError
            swept.append(candidates[j])
            done(j, _fake_rows(candidates[j]))

    return sweep


def test_a_search_resumed_mid_generation_ends_where_the_whole_one_did() -> None:
    """The record (the evaluations) of a search cut in its third generation, some of that
    generation's candidates done out of order, resumed: the same evaluations, in the same
    places, and only the missing candidates swept."""
    whole = _search(5)
    whole.run(ORIGINAL_GAINS, _sweeper(None, []), lambda e: None)
    assert len(whole.evaluations) == 21
    cut = _search(5)
    with pytest.raises(_StopError):
        cut.run(ORIGINAL_GAINS, _sweeper(13, []), lambda e: None)
    kept = [Evaluation.from_dict(json.loads(json.dumps(e.as_dict()))) for e in cut.evaluations]
    assert len(kept) == 13 and {e.generation for e in kept} == {-1, 0, 1, 2}
    swept: list[Candidate] = []
    resumed = _search(5, kept)
    resumed.run(ORIGINAL_GAINS, _sweeper(None, swept), lambda e: None)
    assert len(swept) == 21 - 13
    assert [e.as_dict() for e in resumed.evaluations] == [e.as_dict() for e in whole.evaluations]
    # Another seed's optimiser asks other points: the record is refused, not followed.
    with pytest.raises(ValueError, match="another point than the record's"):
        _search(6, kept).run(ORIGINAL_GAINS, _sweeper(None, []), lambda e: None)


def test_a_candidate_asked_again_is_scored_from_its_first_sweep() -> None:
    """Common random numbers make a sweep a function of the gains: a repeat is not rerun."""
    space = space_for((-1 + 0j, -2 + 0j), None, integral=False)
    requirements = requirements_from(
        None, "test", None, (), None, samples=4, t_final=1.0, inputs=("u",)
    )

    class Repeating:
        """Asks the same two points (one of them twice) every generation."""

        def ask(self) -> list[np.ndarray]:
            return [np.array([0.2, 0.7]), np.array([0.2, 0.7]), np.array([0.9, 0.1])]

        def tell(self, xs: list[np.ndarray], values: list[float]) -> None:
            assert len(values) == 3 and values[0] == values[1]

    swept: list[Candidate] = []

    def sweep(candidates: list[Candidate], done: object) -> None:
        for j, candidate in enumerate(candidates):
            swept.append(candidate)
            error = -float(np.prod([p.real for p in candidate.poles]))  # a number per gains
            rows = [
                {"status": "ok", "final_error": error / (k + 1), "time_saturated": 0.0,
                 "max_abs_u": 1.0, "sample": k}
                for k in range(4)
            ]  # fmt: skip
            done(j, rows)  # type: ignore[operator]

    search = Search(space, requirements, Repeating(), 6, 1.0, ("u",))
    original = Candidate(poles=(-1 + 0j, -2 + 0j), bandwidth=None)
    search.run(original, sweep, lambda evaluation: None)
    assert len(search.evaluations) == 7
    assert [e.index for e in search.evaluations] == list(range(7))
    # The spec's gains, then the two distinct points once: four evaluations were copies.
    assert len(swept) == 3
    by_candidate: dict[Candidate, float] = {}
    for evaluation in search.evaluations:
        value = by_candidate.setdefault(evaluation.candidate, evaluation.score.objective)
        assert evaluation.score.objective == value


def test_a_long_tune_shows_its_progress(tmp_path: Path) -> None:
    """--progress always (what a log gets a line a minute of): candidates done, the best."""
    args = [a for a in PVTOL if a not in ("--progress", "never")]
    ran = run_main(
        "tune", *args, "--evaluations", "6", "--progress", "always", "--out", str(tmp_path / "o")
    )
    assert ran.returncode == 0, ran.stderr
    lines = [line for line in ran.stderr.splitlines() if line.startswith("  tune: ")]
    assert lines[-1].startswith("  tune: 6/6 candidates, best p95(final_error) = ")
    assert "(feasible)" in lines[-1]


def test_a_spec_with_references_is_refused_in_one_line(tmp_path: Path) -> None:
    """The compiled loop has no reference source yet: tune says so, as sweep does."""
    args = ["pvtol_refs" if a == "pvtol" else a for a in PVTOL]
    ran = run_main("tune", *args, "--out", str(tmp_path / "out"))
    assert ran.returncode == EXIT_BAD_SPEC
    lines = ran.stderr.strip().splitlines()
    assert len(lines) == 1 and "references: the compiled loop of sweep and tune" in lines[0]
    assert not (tmp_path / "out").exists()


def test_odd_characters_in_the_paths(tmp_path: Path) -> None:
    """A spec and an output folder whose names have spaces, quotes and accents."""
    folder = tmp_path / "my 'robots' é"
    folder.mkdir()
    spec = folder / "pvtol copy.toml"
    spec.write_text((EXAMPLES / "pvtol.toml").read_text())
    args = [str(spec) if a == "pvtol" else a for a in PVTOL]
    args += ["--samples", "4", "--check-samples", "4"]  # the paths are the subject
    out = folder / "tuned out"
    ran = run_main("tune", *args, "--evaluations", "6", "--out", str(out))
    assert ran.returncode == 0, ran.stderr
    assert tomllib.loads((out / TUNED).read_text())["name"] == "pvtol"
    assert run_main("tune", "--resume", str(out)).returncode == 0  # complete: nothing to do
