"""The confirmation protocol: seeds follow the freeze commit, paired CIs, pooled seeds, frozen records only."""
import shutil
import subprocess

import pytest

from selfseg.eval import confirm
from selfseg.eval.cli import main as evaluate
from selfseg.eval.confirm import (BEGIN, DEVELOPMENT_SEEDS, END, NAMED_BEGIN, ROOT, SEED_RESULTS_DIR, FreezeError,
                                  board, check_checkout, freeze, fresh_seeds, frozen_paths_differ, main, read_freeze)
from selfseg.eval.layout import FAILED_JSON
from selfseg.eval.leaderboard import BEGIN as BUILD_BEGIN
from selfseg.eval.pooled import paired, pooled_videos, score
from selfseg.eval.provenance import cpu_model
from selfseg.fileio import read_json, write_json


def _git(*args):
    return subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True, check=True).stdout.strip()


def _videos(values, frames=4):
    return {f"s/{i:06d}": {"IoU": v, "n_frames": frames} for i, v in enumerate(values)}


def test_fresh_seeds_follow_the_freeze_commit_and_avoid_development_seeds():
    a = fresh_seeds("0" * 40)
    assert a == fresh_seeds("0" * 40) and len(set(a)) == 3
    assert all(100_000 <= s < 1_000_000 and s not in DEVELOPMENT_SEEDS for s in a)
    assert fresh_seeds("1" + "0" * 39) != a  # a new freeze draws new seeds
    assert len(fresh_seeds("0" * 40, 5)) == 5 and fresh_seeds("0" * 40, 5)[:3] == a
    # an earlier freeze's seeds are spent: the draw skips them and takes the next
    assert fresh_seeds("0" * 40, 3, frozenset(a[:1])) == fresh_seeds("0" * 40, 4)[1:]


def test_paired_difference_verdicts_on_known_videos():
    base = [0.5, 0.6, 0.7, 0.8, 0.55, 0.65]
    up = paired(_videos([b + 0.1 for b in base]), _videos(base))
    assert up["mean"] == pytest.approx(0.1) and up["ci95"][0] == pytest.approx(0.1) and up["verdict"] == "holds"
    assert up["wins"] == 6 and up["n_videos"] == 6 and up["n_unpaired"] == 0
    assert paired(_videos(base), _videos([b + 0.1 for b in base]))["verdict"] == "reversed"
    mixed = paired(_videos([b + d for b, d in zip(base, (0.2, -0.2, 0.1, -0.1, 0.05, -0.05))]), _videos(base))
    assert mixed["verdict"] == "inside the noise" and mixed["ci95"][0] < 0 < mixed["ci95"][1]
    assert mixed["wins"] == 3 and mixed["losses"] == 3
    with pytest.raises(ValueError, match="same frames"):
        paired(_videos(base, frames=4), _videos(base, frames=5))
    weighted = score({"a": {"IoU": 1.0, "n_frames": 3}, "b": {"IoU": 0.0, "n_frames": 1}})
    assert weighted["mean"] == pytest.approx(0.75) and weighted["n_frames"] == 4


@pytest.fixture(scope="module")
def runs(analytic_dataset, tmp_path_factory):
    """Two 'fresh seeds' (the analytic dataset twice): the oracle as `ours`, one segment as `depth-clustering`."""
    root = tmp_path_factory.mktemp("confirm")
    head = _git("rev-parse", "HEAD")
    for seed in (101, 202):
        out = root / SEED_RESULTS_DIR.format(seed=seed)
        for method, name in (("oracle", "ours"), ("one-segment", "depth-clustering")):
            assert evaluate(["--method", method, "--name", name, "--data", str(analytic_dataset), "--frame-stride",
                             "3", "--out", str(out), "--quiet"]) == 0
        for path in out.glob("scores/*/*/fold*.json"):  # as if run from a clean checkout of the freeze commit
            rec = read_json(path)
            write_json(path, {**rec, "git": {"commit": head, "dirty": False}})
    rec = {"preset": "analytic", "commit": head, "committed_utc": "2026-01-01T00:00:00+00:00",
           "recorded_utc": "2026-01-01T00:00:01+00:00", "seeds": [101, 202, 303]}
    return root, rec


def test_board_pools_the_fresh_seeds_and_keeps_the_build_section(runs, tmp_path):
    root, rec = runs
    page = tmp_path / "analytic.md"
    page.write_text(f"# mine\n\n{BUILD_BEGIN}\nbuilt tables\n<!-- END GENERATED -->\n\nnotes\n")
    board(rec, root, [("seed 0", root / SEED_RESULTS_DIR.format(seed=101))], page)
    text = page.read_text()
    assert "built tables" in text and "notes" in text and text.count(BEGIN) == 1
    assert "2 of 3 seeds finished" in text and "seed 0 (development)" in text and "pooled, 2 fresh seeds" in text
    claim = next(line for line in text.splitlines() if line.startswith("| ours − depth-clustering"))
    assert "**holds**" in claim and "6 of 6" in claim  # 3 test videos per seed, oracle beats one segment on each
    assert "| ours | 1.000 (1.000–1.000) |" in text
    board(rec, root, [("seed 0", root / SEED_RESULTS_DIR.format(seed=101))], page)
    assert page.read_text() == text  # idempotent


def test_a_second_freezes_board_is_a_section_of_its_own(runs, tmp_path):
    """A later freeze of the preset writes its own section (its name in the markers and the title) and leaves the
    first freeze's section as it was; rebuilding either leaves the other alone."""
    root, rec = runs
    page = tmp_path / "analytic.md"
    board(rec, root, [], page)
    first = page.read_text()
    board({**rec, "name": "analytic-2"}, root, [], page)
    text = page.read_text()
    assert text.startswith(first.rstrip("\n")) and text.count(BEGIN) == 1 and text.count(END) == 1
    assert text.count(NAMED_BEGIN.format(name="analytic-2")) == 1
    assert "## Confirmation on fresh seeds: freeze `analytic-2`" in text and "`leaderboards/analytic-2-freeze.json`" in text
    board(rec, root, [], page)
    assert page.read_text() == text


def test_compare_gives_one_seeds_paired_claims_with_verdicts(runs, capsys):
    """`confirm compare` on one results folder: the oracle (as ours) against one segment holds on every video;
    a run the folder lacks is one line and exit 2."""
    root, _ = runs
    results = root / SEED_RESULTS_DIR.format(seed=101)
    assert main(["compare", "--results", str(results), "--b", "depth-clustering"]) == 0
    (line,) = capsys.readouterr().out.strip().splitlines()
    assert line.startswith("ours − depth-clustering: +") and line.endswith(": holds")
    assert main(["compare", "--results", str(results), "--b", "ours-v2"]) == 2
    assert capsys.readouterr().err.strip() == f"confirm: error: {results}: no 2-D results of 'ours-v2'"


def test_compare_against_another_folder_pairs_every_run_both_have(runs, capsys):
    """Two folders of the same data (here two 'seeds' of the analytic dataset, as if one seed run by two commits):
    each run in both is paired with itself, unchanged scores read +0.000 inside the noise, and a run in one
    folder only is named."""
    root, _ = runs
    a, b = (root / SEED_RESULTS_DIR.format(seed=s) for s in (101, 202))
    assert main(["compare", "--results", str(a), "--against", str(b)]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert sorted(line.split(":")[0] for line in lines) == ["depth-clustering", "ours"]
    assert all("= +0.000 IoU" in line and line.endswith("over 3 test videos: inside the noise") for line in lines)
    with pytest.raises(SystemExit):
        main(["compare", "--results", str(a)])  # neither --b nor --against


def test_board_reports_the_drop_with_noisy_depth_paired_per_video(runs, tmp_path):
    """The noisy variant of one fresh seed (here: `ours` becomes one segment, `depth-clustering` stays one
    segment): `ours` drops on every video, depth-clustering does not move, and the claims are retested."""
    root, rec = runs
    noisy_root = tmp_path / "noisy"
    exact = root / SEED_RESULTS_DIR.format(seed=101)
    for path in exact.glob("scores/*/depth-clustering/fold*.json"):  # one segment's records, under both names
        for name in ("ours", "depth-clustering"):
            to = noisy_root / SEED_RESULTS_DIR.format(seed=101) / path.relative_to(exact).parent.parent / name / path.name
            to.parent.mkdir(parents=True, exist_ok=True)
            write_json(to, {**read_json(path), "name": name})
    page = tmp_path / "analytic.md"
    board(rec, root, [], page, noisy_root)
    lines = page.read_text().splitlines()
    assert "### The same seeds with noisy depth (analytic-noisy)" in lines and "(1 of 3 seeds finished)" in page.read_text()
    ours = next(line for line in lines if line.startswith("| ours | 1.000 | "))
    assert ours.endswith("| 3 of 3 | drops |")  # paired over seed 101's videos only, not seed 202's
    dc = next(line for line in lines if line.startswith("| depth-clustering | ") and "| +0.000 |" in line)
    assert dc.endswith("| 0 of 3 | inside the noise |")
    noisy_claim = [line for line in lines if line.startswith("| ours − depth-clustering")][-1]
    assert "| 0 of 3 | **inside the noise** |" in noisy_claim
    board(rec, root, [], page)  # without the noisy runs the subsection goes
    assert "noisy depth" not in page.read_text()



def test_where_ours_did_not_run_the_claims_are_v2s(runs, tmp_path):
    """Seeds without `ours` (a preset whose matching does not terminate): the board says so and tests V2's claims
    (here the oracle's records filed as V2), in the exact and in the noisy section."""
    root, rec = runs
    v2_root = tmp_path / "v2"
    for seed in (101, 202):
        src = root / SEED_RESULTS_DIR.format(seed=seed)
        for path in src.glob("scores/*/*/fold*.json"):
            name = {"ours": "ours-v2"}.get(path.parent.name, path.parent.name)
            to = v2_root / SEED_RESULTS_DIR.format(seed=seed) / path.relative_to(src).parent.parent / name / path.name
            to.parent.mkdir(parents=True, exist_ok=True)
            write_json(to, {**read_json(path), "name": name})
    page = tmp_path / "analytic.md"
    board(rec, v2_root, [], page, v2_root)
    text = page.read_text()
    assert "`ours` did not run on these seeds, so the claims below are `ours-v2`'s" in text
    claims = [line for line in text.splitlines() if line.startswith("| ours-v2 − ")]
    assert len(claims) == 2 and all(c.startswith("| ours-v2 − depth-clustering |") for c in claims)
    assert "**holds**" in claims[0] and "6 of 6" in claims[0]
    assert "| ours − " not in text and "| ours-v2 − ours-v2" not in text
    board(rec, root, [], page)  # with `ours` the claims are its own again
    assert "did not run on these seeds" not in page.read_text()

def _fail(results, name: str, fold: int, task: str = "2d") -> None:
    """Turn run ``name``'s fold (or a made-up 3-D row) into a failure record, as evaluate writes it."""
    if task == "2d":
        path = next(results.glob(f"scores/*/{name}/fold{fold}.json"))
        rec = read_json(path)
        path.unlink()
    else:
        rec = {**read_json(next(results.glob("scores/*/*/fold0.json"))), "name": name, "task": task, "fold": fold}
    rec = {k: v for k, v in rec.items() if k not in ("metrics", "per_video", "ci95")}
    write_json(results / FAILED_JSON.format(dataset=rec["dataset"]["key"], name=name, fold=fold),
               {**rec, "failure": {"kind": "budget", "message": "matching used more than its CPU budget"}})


def test_a_run_over_its_budget_is_shown_failed_and_its_claims_need_two_seeds(runs, tmp_path):
    """`ours` fails fold 1 under its budget on one of three seeds: that seed's cell says so, the pooled cell holds
    the other two seeds, and the claim is tested on those two; failing on a second seed leaves one, so the claim
    is not tested. A failed Table II row is shown failed."""
    import shutil

    root, rec = runs
    three = tmp_path / "three"
    for seed, src in ((101, 101), (202, 202), (303, 101)):
        shutil.copytree(root / SEED_RESULTS_DIR.format(seed=src), three / SEED_RESULTS_DIR.format(seed=seed))
    _fail(three / SEED_RESULTS_DIR.format(seed=202), "ours", 1)
    _fail(three / SEED_RESULTS_DIR.format(seed=202), "ours-matching", 0, task="3d")
    page = tmp_path / "analytic.md"
    board(rec, three, [], page)
    lines = page.read_text().splitlines()
    ours = next(line for line in lines if line.startswith("| ours | "))
    assert ours == ("| ours | 1.000 (1.000–1.000) | failed: over budget (fold 1) | 1.000 (1.000–1.000) | "
                    "1.000 (1.000–1.000), 2 of 3 seeds |")
    claim = next(line for line in lines if line.startswith("| ours − depth-clustering"))
    assert "6 of 6 (2 of 3 seeds: a failure on seed 202)" in claim and "**holds**" in claim
    assert "| ours-matching | — | failed: over budget | — |" in lines
    assert "not at all with fewer than 2 such seeds" in page.read_text()

    _fail(three / SEED_RESULTS_DIR.format(seed=303), "ours", 0)
    board(rec, three, [], page)
    claim = next(line for line in page.read_text().splitlines() if line.startswith("| ours − depth-clustering"))
    assert claim == ("| ours − depth-clustering | — | — | — | **not tested**: ours failed under its budget on seed 202, "
                     "seed 303, 1 seed left (needs 2) |")


def test_board_refuses_a_record_from_code_that_moved_since_the_freeze(runs, tmp_path):
    root, rec = runs
    first = _git("rev-list", "--max-parents=0", "HEAD").splitlines()[0]
    path = next((root / SEED_RESULTS_DIR.format(seed=202)).glob("scores/*/ours/fold1.json"))
    good = read_json(path)
    try:
        write_json(path, {**good, "git": {"commit": first, "dirty": False}})
        with pytest.raises(FreezeError, match="seed 202, run ours, fold 1: ran at"):
            board(rec, root, [], tmp_path / "x.md")
        write_json(path, {**good, "git": {"commit": rec["commit"], "dirty": True}})
        with pytest.raises(FreezeError, match=r"\(dirty\)"):
            board(rec, root, [], tmp_path / "x.md")
    finally:
        write_json(path, good)


def test_a_checkout_whose_code_moved_since_the_freeze_may_not_run_it():
    first = _git("rev-list", "--max-parents=0", "HEAD").splitlines()[0]
    assert frozen_paths_differ(_git("rev-parse", "HEAD"), "HEAD") == []
    with pytest.raises(FreezeError, match="that is a new freeze"):
        check_checkout({"commit": first})
    assert pooled_videos([], "ours") == {}


def test_only_uncommitted_code_or_configs_stop_a_frozen_checkout(tmp_path, monkeypatch):
    """A board written into leaderboards/ (what confirm.sh does at its end) or a note under docs/ leaves the checkout
    runnable; a modified code file or an untracked config does not, and the refusal names it."""
    def git(*args):
        subprocess.run(["git", "-C", str(tmp_path), *args], check=True, capture_output=True)

    for path, text in (("method/x.py", "a = 1\n"), ("configs/c.yaml", "k: 1\n"), ("leaderboards/calibrated.md", "# b\n")):
        (tmp_path / path).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / path).write_text(text)
    git("init", "-q")
    git("add", ".")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "freeze")
    monkeypatch.setattr(confirm, "ROOT", tmp_path)
    rec = {"commit": confirm._git("rev-parse", "HEAD")}
    (tmp_path / "leaderboards/calibrated.md").write_text("# the board, rebuilt\n")
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs/note.md").write_text("a note\n")
    check_checkout(rec)
    (tmp_path / "method/x.py").write_text("a = 2\n")
    with pytest.raises(FreezeError, match=r"uncommitted changes \(method/x\.py\)"):
        check_checkout(rec)
    git("checkout", "method/x.py")
    (tmp_path / "configs/new.yaml").write_text("k: 2\n")
    with pytest.raises(FreezeError, match=r"\(configs/new\.yaml\)"):
        check_checkout(rec)


def test_a_preset_frozen_twice_keeps_both_records_and_spends_no_seed_twice(tmp_path, monkeypatch):
    """The first freeze is the preset's name; freezing it again under that name is refused; a second freeze is
    `<preset>-2`, its own record, and draws none of the first's seeds; any other name is refused."""
    def git(*args):
        subprocess.run(["git", "-C", str(tmp_path), "-c", "user.name=t", "-c", "user.email=t@t", *args], check=True,
                       capture_output=True)

    (tmp_path / "configs").mkdir()
    (tmp_path / "configs/c.yaml").write_text("k: 1\n")
    git("init", "-q")
    git("add", ".")
    git("commit", "-qm", "configs")
    monkeypatch.setattr(confirm, "ROOT", tmp_path)
    first = freeze("analytic")
    assert first["name"] == "analytic" and (tmp_path / "leaderboards/analytic-freeze.json").is_file()
    git("add", ".")
    git("commit", "-qm", "freeze record")
    with pytest.raises(FreezeError, match="already recorded"):
        freeze("analytic")
    with pytest.raises(FreezeError, match="expected 'analytic'"):
        freeze("analytic", name="other")
    (tmp_path / "configs/c.yaml").write_text("k: 2\n")
    git("commit", "-qam", "a change after the freeze")
    second = freeze("analytic", name="analytic-2")
    assert second["commit"] != first["commit"] and not set(second["seeds"]) & set(first["seeds"])
    assert read_freeze("analytic", "analytic-2")["seeds"] == second["seeds"]
    assert read_freeze("analytic")["seeds"] == first["seeds"]
    assert main(["seeds", "--preset", "analytic", "--freeze", "analytic-2"]) == 0


def test_archive_and_restore_carry_the_finished_folds_to_another_machine(runs, tmp_path):
    """Archive copies each seed's finished fold records (not a fold still running) with a README of names and fold
    counts only; restored into an empty runs folder they give the same board; an archive never drops a record."""
    root, rec = runs
    rec = {**rec, "name": "analytic"}
    src = tmp_path / "runs"
    shutil.copytree(root, src)
    running = src / SEED_RESULTS_DIR.format(seed=101) / "scores/x/ours-v2/fold0.frames.jsonl"
    running.parent.mkdir(parents=True)
    running.write_text("{}\n")  # a fold whose JSON is not written yet
    (src / "seed-101/timings.tsv").write_text("generate\t3\t3\t100\nours\t9\t9\t100\ntotal\t20\t\n")
    (src / SEED_RESULTS_DIR.format(seed=303)).mkdir(parents=True)  # a seed begun, nothing finished: not archived
    dest = tmp_path / "archive"
    lines = confirm.archive(rec, src, dest)
    assert [line.split(":")[0] for line in lines] == ["seed 101", "seed 202"] and not (dest / "seed-303").exists()
    n = len(list((src / "seed-101/results/scores").rglob("fold*.json")))
    assert n == 6 and len(list((dest / "seed-101/results/scores").rglob("fold*.json"))) == n
    assert not (dest / "seed-101/results/scores/x").exists()
    readme = (dest / "seed-101/README.md").read_text()
    assert "**finished**" in readme and "`ours` 3 scored" in readme and "`depth-clustering` 3 scored" in readme
    assert "1.000" not in readme and "IoU" not in readme  # names and counts, no score
    assert f"Made on: {cpu_model()} (" in readme  # the CPU type its data's RGB needs to be kept on resuming
    assert "**not finished**" in (dest / "seed-202/README.md").read_text()  # no timings: cut off or still going
    assert confirm.archive(rec, src, dest) == lines  # idempotent
    # a resumed queue scoring a finished fold again (same run: new time stamp and timings) leaves the archive as it
    # was, README included; a record of another run (here: another commit) replaces the archived one
    redone = sorted((src / "seed-101/results/scores").rglob("fold*.json"))[0]
    archived = dest / redone.relative_to(src)
    before, readme = archived.read_bytes(), (dest / "seed-101/README.md").read_bytes()
    r = read_json(redone)
    write_json(redone, {**r, "created_utc": "2099-01-01T00:00:00+00:00", "timings": {**r["timings"], "fit_s": 1e6}})
    assert confirm.archive(rec, src, dest) == lines
    assert archived.read_bytes() == before and (dest / "seed-101/README.md").read_bytes() == readme
    write_json(redone, {**r, "git": {**r["git"], "commit": "f" * 40}})
    confirm.archive(rec, src, dest)
    assert read_json(archived)["git"]["commit"] == "f" * 40
    write_json(redone, r)  # back to the freeze's commit, which the board checks
    confirm.archive(rec, src, dest)
    confirm.archive(rec, src, tmp_path / "noisy", noisy=True)  # noisy rows keep no timings: no state claimed
    assert "finished**" not in (tmp_path / "noisy/seed-101/README.md").read_text()

    fresh = tmp_path / "fresh"  # another machine: nothing but the archive
    with pytest.raises(FreezeError, match="confirm restore"):
        (fresh / "seed-101/results").mkdir(parents=True)
        confirm.archive(rec, fresh, dest)
    assert "6 fold records restored" in confirm.restore(rec, dest, fresh)[0]
    assert (fresh / "seed-101/timings.tsv").read_text() == (src / "seed-101/timings.tsv").read_text()
    a, b = tmp_path / "a.md", tmp_path / "b.md"
    board(rec, src, [], a)
    board(rec, fresh, [], b)
    assert a.read_text() == b.read_text()
    assert "0 fold records restored" in confirm.restore(rec, dest, fresh)[0]  # what is there stays


def test_archive_names_the_cpu_of_records_made_before_records_named_it(runs, tmp_path):
    """A freeze from before records named their CPU: archive notes this machine for the records it copies from its
    own run folder (made_on.json, named in the README), and not for records restored from another machine."""
    root, rec = runs
    rec = {**rec, "name": "analytic"}
    src = tmp_path / "runs"
    shutil.copytree(root, src)
    for path in (src / "seed-101/results").rglob("fold*.json"):
        write_json(path, {k: v for k, v in read_json(path).items() if k != "cpu"})
    dest = tmp_path / "archive"
    confirm.archive(rec, src, dest)
    made_on = read_json(dest / "seed-101/made_on.json")
    assert len(made_on) == 6 and {m["model"] for m in made_on.values()} == {cpu_model()}
    assert f"Made on: {cpu_model()} (" in (dest / "seed-101/README.md").read_text()
    assert "the machine that archived it" in (dest / "seed-101/README.md").read_text()
    assert not (dest / "seed-202/made_on.json").exists()  # its records name their CPU themselves
    other = {"model": "Another CPU", "flags": ["avx2"], "source": "the machine that archived it from its run"}
    write_json(dest / "seed-101/made_on.json", {k: other for k in made_on})  # as archived on another machine
    fresh = tmp_path / "fresh"
    confirm.restore(rec, dest, fresh)
    for path in (fresh / "seed-202/results").rglob("fold*.json"):  # a fold run here after the restore
        write_json(path, {k: v for k, v in read_json(path).items() if k != "cpu"} | {"git": {"commit": "e" * 40}})
        break
    confirm.archive(rec, fresh, dest)
    assert {m["model"] for m in read_json(dest / "seed-101/made_on.json").values()} == {"Another CPU"}  # restored: kept
    made_here = read_json(dest / "seed-202/made_on.json")  # the one record written from this run folder
    assert len(made_here) == 1 and next(iter(made_here.values())) == next(iter(made_on.values()))
