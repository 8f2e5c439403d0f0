"""plots/: figures and tables from tiny real runs, numbers checked against the logged scalars read independently."""

import csv
import dataclasses
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch

import cascade_ppo_continuous as cpc
import ppo_baseline
from helpers import ROOT, built_once, read_scalars
from plots import analyze, common, fallback, final_performance, learning_curves, members

TINY = dict(env_id="Hopper-v4", num_steps=256, num_minibatches=4, update_epochs=2, eval_every=512, eval_episodes=2,
            quiet=True)
SEEDS = (1, 2)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """2 seeds of Cascade (n=2, k=1024) and 2 seeds of PPO (2048 steps) on Hopper-v4, a few seconds each (made by
    one xdist worker, read by all)."""
    return built_once(tmp_path_factory, "plots_runs", make_runs)


def make_runs(folder):
    track = str(folder)
    cascade, baseline, second_net = [], [], {}

    def capture(state):
        if state["iteration"] == 2:
            second_net.update({k: v.detach().clone() for k, v in state["actor"].state_dict().items()})

    for seed in SEEDS:
        hook = capture if seed == SEEDS[0] else None
        cascade.append(cpc.train(cpc.Args(seed=seed, n=2, k=1024, track_dir=track, **TINY), on_iteration_start=hook)
                       ["run_dir"])
        baseline.append(ppo_baseline.train(ppo_baseline.Args(seed=seed, total_timesteps=2048, track_dir=track, **TINY))
                        ["run_dir"])
    return {"track": track, "cascade": cascade, "baseline": baseline, "second_net": second_net}


def read_csv(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def assert_figures(paths, *stems):
    for stem in stems:
        png, pdf = [p for p in paths if os.path.splitext(p)[0].endswith(stem) and p.endswith((".png", ".pdf"))]
        with open(png, "rb") as f:
            assert f.read(8) == b"\x89PNG\r\n\x1a\n"
        with open(pdf, "rb") as f:
            assert f.read(5) == b"%PDF-"
        assert os.path.getsize(png) > 5000 and os.path.getsize(pdf) > 2000


def last_values(run_dirs, tag):
    return [read_scalars(d)[tag][-1][1] for d in run_dirs]


def test_learning_curves_match_logged_returns(runs, tmp_path):
    paths = learning_curves.main(learning_curves.Args(runs=(runs["track"],), out=str(tmp_path)))
    assert_figures(paths, "learning_curves")
    rows = read_csv(tmp_path / "learning_curves.csv")
    for label, dirs in (("Cascade", runs["cascade"]), ("PPO", runs["baseline"])):
        curve = [r for r in rows if r["experiment"] == label and r["env"] == "Hopper-v4"]
        assert [int(r["step"]) for r in curve] == [0, 512, 1024, 1536, 2048]
        values = np.array(last_values(dirs, "eval/episodic_return"))
        assert float(curve[-1]["mean"]) == pytest.approx(values.mean(), rel=1e-6)
        assert float(curve[-1]["sem"]) == pytest.approx(values.std(ddof=1) / np.sqrt(2), rel=1e-6)
        assert curve[-1]["seeds"] == "2"
    assert f"{np.mean(last_values(runs['cascade'], 'eval/episodic_return')):.1f}" in \
        (tmp_path / "learning_curves.md").read_text()
    # the base net added at k=1024 is read from cascade/size
    assert common.net_added_steps(common.read_run(runs["cascade"][0])) == [1024]


def test_one_seed_works(runs, tmp_path):
    one = tmp_path / "one"
    shutil.copytree(runs["cascade"][0], one / os.path.basename(runs["cascade"][0]))
    paths = learning_curves.main(learning_curves.Args(runs=(str(one),), out=str(tmp_path / "out")))
    assert_figures(paths, "learning_curves")
    last = read_csv(tmp_path / "out" / "learning_curves.csv")[-1]
    assert (last["seeds"], float(last["sem"])) == ("1", 0.0)
    assert float(last["mean"]) == pytest.approx(last_values(runs["cascade"][:1], "eval/episodic_return")[0])
    row = open(tmp_path / "out" / "learning_curves.md").read().splitlines()[-1]
    assert "±" not in row, row  # one seed has no standard error (the table said "± 0.0")


def test_a_relaunched_seed_counts_once(runs, tmp_path, capsys):
    track = tmp_path / "runs"
    shutil.copytree(runs["track"], track)
    relaunch = os.path.basename(runs["cascade"][0]).rsplit("__", 1)[0] + "__9999999999"
    shutil.copytree(runs["cascade"][0], track / relaunch)
    learning_curves.main(learning_curves.Args(runs=(str(track),), out=str(tmp_path / "out")))
    assert {r["seeds"] for r in read_csv(tmp_path / "out" / "learning_curves.csv")} == {"2"}
    assert f"using {relaunch}" in capsys.readouterr().err


def test_a_relaunch_that_stopped_early_does_not_replace_the_finished_run(tmp_path, capsys):
    """Two runs of one seed: the longer counts, even when the shorter was started later (a relaunch that was
    killed); of two equally long ones, the newer."""
    root = tmp_path / "runs"
    finished = write_fake_run(root, "Hopper-v4__ppo_baseline__1__1700000000", [0, 4096, 8192], 100.0)
    write_fake_run(root, "Hopper-v4__ppo_baseline__1__1800000000", [0, 4096], 5000.0)  # relaunched, killed
    write_fake_run(root, "Hopper-v4__ppo_baseline__2__1700000000", [0, 4096, 8192], 300.0)
    write_fake_run(root, "Hopper-v4__ppo_baseline__2__1800000000", [0, 4096, 8192], 200.0)  # relaunched, finished
    final_performance.main(final_performance.Args(runs=(str(root),), out=str(tmp_path / "out"),
                                                  baseline="ppo_baseline", reps=50))
    assert f"using {os.path.basename(finished)}, not Hopper-v4__ppo_baseline__1__1800000000" in capsys.readouterr().err
    (row,) = read_csv(tmp_path / "out" / "final_performance.csv")
    assert (row["seeds"], float(row["mean"])) == ("2", 150.0), row


# The statistics of plots/final_performance.py, written out in numpy: the cross-check of what rliable computes there.
def reference_iqm(scores):
    """Interquartile mean along the last axis: drop the lowest and highest floor(n/4), average the rest."""
    n = scores.shape[-1]
    cut = int(0.25 * n)
    return np.sort(scores, axis=-1)[..., cut: n - cut].mean(-1)


def reference_improvement(x, y):
    """P(X > Y) along the last axes: share of pairs (x_i, y_j) with x_i > y_j, ties counting 1/2."""
    diff = x[..., :, None] - y[..., None, :]
    return ((diff > 0) + 0.5 * (diff == 0)).mean((-2, -1))


def reference_bootstrap(strata, statistic, reps, rng):
    """`reps` values of `statistic`, each on a resample (with replacement, same size) of every stratum."""
    return statistic([s[rng.integers(0, len(s), size=(reps, len(s)))] for s in strata])


def reference_ci(values, confidence):
    tail = 100 * (1 - confidence) / 2
    low, high = np.percentile(values, [tail, 100 - tail])
    return float(low), float(high)


def test_reference_statistics():
    assert reference_iqm(np.arange(1.0, 9.0)) == pytest.approx(4.5)  # mean of 3, 4, 5, 6
    assert reference_iqm(np.array([0.0, 1.0, 2.0, 100.0])) == pytest.approx(1.5)  # the outlier is cut
    assert reference_iqm(np.array([3.0, 5.0])) == pytest.approx(4.0)  # < 4 seeds: the mean
    x, y = np.array([1.0, 2.0, 3.0]), np.array([2.0, 0.0])
    # pairs: (1,2)<, (1,0)>, (2,2)=, (2,0)>, (3,2)>, (3,0)> -> (4 + 0.5) / 6
    assert reference_improvement(x, y) == pytest.approx(4.5 / 6)
    rng = np.random.default_rng(0)
    data = [rng.normal(size=10), rng.normal(size=10) + 5]
    boot = reference_bootstrap(data, lambda rs: np.concatenate(rs, axis=1).mean(1), 4000, np.random.default_rng(1))
    # each replicate keeps 10 runs from each stratum: the bootstrap mean centers on the data's mean
    assert boot.shape == (4000,) and boot.mean() == pytest.approx(np.concatenate(data).mean(), abs=0.05)
    low, high = reference_ci(boot, 0.95)
    assert low < np.concatenate(data).mean() < high
    constant = reference_bootstrap([np.full(5, 2.0)], lambda rs: rs[0].mean(1), 100, np.random.default_rng(0))
    assert reference_ci(constant, 0.95) == (2.0, 2.0)


@pytest.mark.parametrize("seeds", [3, 7])
def test_rliable_estimates_match_the_numpy_reference(seeds):
    """IQM, probability of improvement and their stratified bootstrap CIs as final_performance.py gets them from
    rliable, against the reference above: equal point estimates; CIs equal up to the bootstrap's own noise."""
    rng = np.random.default_rng(seeds)
    x = rng.normal(1.0, 0.3, size=(seeds, 2)) * [1.0, 3.0]  # runs x envs, envs on different scales
    y = rng.normal(0.9, 0.3, size=(seeds, 2)) * [1.0, 3.0]
    args = final_performance.Args(reps=4000)
    spread = x.max() - x.min()
    # per env, and pooled over envs (the bootstrap stratified by env)
    for matrix, strata in [(x[:, :1], [x[:, 0]]), (x, [x[:, 0], x[:, 1]])]:
        point, (low, high) = final_performance.interval_estimate(matrix, final_performance.metrics.aggregate_iqm,
                                                                 args, 0)
        assert point == pytest.approx(reference_iqm(matrix.ravel()))
        boot = reference_bootstrap(strata, lambda rs: reference_iqm(np.concatenate(rs, axis=1)), 20_000,
                                   np.random.default_rng(1))
        assert np.allclose((low, high), reference_ci(boot, 0.95), atol=0.05 * spread)
    # rliable's probability of improvement runs scipy's Mann-Whitney test per replicate and env: fewer replicates
    point, (low, high) = final_performance.interval_estimate((x, y), final_performance.metrics.probability_of_improvement,
                                                             final_performance.Args(reps=1000), 1)
    assert point == pytest.approx(np.mean([reference_improvement(x[:, e], y[:, e]) for e in range(2)]))
    boot = reference_bootstrap([x[:, 0], y[:, 0], x[:, 1], y[:, 1]],
                               lambda rs: np.mean([reference_improvement(a, b) for a, b in zip(rs[0::2], rs[1::2])], 0),
                               20_000, np.random.default_rng(2))
    assert np.allclose((low, high), reference_ci(boot, 0.95), atol=0.08)


def test_bootstrap_cis_do_not_depend_on_numpys_global_random_state():
    """rliable draws its bootstrap indices from numpy's global generator: final_performance.py seeds it per
    estimate, and leaves it as it was, so that a figure rebuilt from the same runs has the same CIs."""
    x = np.random.default_rng(0).normal(size=(5, 2))
    estimates = []
    for global_seed in (0, 1):
        np.random.seed(global_seed)
        before = np.random.get_state()[1].copy()
        estimates.append([final_performance.interval_estimate(scores, final_performance.metrics.aggregate_iqm,
                                                              final_performance.Args(reps=200), 0)
                          for scores in (x[:, :1], x)])
        assert np.array_equal(np.random.get_state()[1], before)
    assert estimates[0] == estimates[1]


def test_final_performance_matches_logged_returns(runs, tmp_path):
    paths = final_performance.main(final_performance.Args(runs=(runs["track"],), out=str(tmp_path), reps=500))
    assert_figures(paths, "final_performance", "final_performance_improvement")
    rows = {r["experiment"]: r for r in read_csv(tmp_path / "final_performance.csv")}
    cascade = np.array(last_values(runs["cascade"], "eval/episodic_return"))
    ppo = np.array(last_values(runs["baseline"], "eval/episodic_return"))
    assert float(rows["Cascade"]["iqm"]) == pytest.approx(cascade.mean(), rel=1e-6)  # 2 seeds: IQM = mean
    assert float(rows["PPO"]["mean"]) == pytest.approx(ppo.mean(), rel=1e-6)
    low, high = float(rows["Cascade"]["iqm_ci_low"]), float(rows["Cascade"]["iqm_ci_high"])
    assert cascade.min() - 1e-6 <= low <= high <= cascade.max() + 1e-6
    expected = np.mean([(c > p) + 0.5 * (c == p) for c in cascade for p in ppo])
    assert float(rows["Cascade"]["p_improvement"]) == pytest.approx(expected)
    assert "P(better than PPO)" in (tmp_path / "final_performance.md").read_text()


def write_synthetic_run(track, env, exp, seed, final):
    """A run folder with the logs a training script writes, evaluation returns rising linearly to `final`."""
    from torch.utils.tensorboard import SummaryWriter

    writer = SummaryWriter(os.path.join(track, f"{env}__{exp}__{seed}__{1700000000 + seed}"))
    writer.add_text("hyperparameters", f"|param|value|\n|-|-|\n|exp_name|{exp}|\n|seed|{seed}|\n|env_id|{env}|")
    for step in range(0, 50_001, 10_000):
        writer.add_scalar("eval/episodic_return", final * step / 50_000, step)
    writer.close()


def test_final_performance_over_several_envs_and_ten_seeds(tmp_path):
    track = str(tmp_path / "runs")
    finals = {}
    for env, scale in (("Hopper-v4", 1000.0), ("Walker2d-v4", 3000.0)):
        for exp, shift in (("cascade_ppo_continuous", 0.2), ("ppo_baseline", 0.0)):
            finals[(env, exp)] = scale * (1 + shift + 0.1 * np.sin(np.arange(1, 11)))
            for seed, final in enumerate(finals[(env, exp)], start=1):
                write_synthetic_run(track, env, exp, seed, final)
    paths = final_performance.main(final_performance.Args(runs=(track,), out=str(tmp_path), reps=300))
    assert_figures(paths, "final_performance", "final_performance_improvement", "final_performance_profile")
    rows = {(r["env"], r["experiment"]): r for r in read_csv(tmp_path / "final_performance.csv")}
    pooled = ("all envs", "Cascade")
    for env in ("Hopper-v4", "Walker2d-v4"):
        scores = np.sort(finals[(env, "cascade_ppo_continuous")])
        assert float(rows[(env, "Cascade")]["iqm"]) == pytest.approx(scores[2:8].mean())  # 10 seeds: drop 2 + 2
        # its CI bootstraps the 10 seeds (measured within 0.07 of the reference's width at 300 replicates)
        boot = reference_bootstrap([scores], lambda rs: reference_iqm(rs[0]), 20_000, np.random.default_rng(1))
        low, high = reference_ci(boot, 0.95)
        ci = float(rows[(env, "Cascade")]["iqm_ci_low"]), float(rows[(env, "Cascade")]["iqm_ci_high"])
        assert np.allclose(ci, (low, high), atol=0.2 * (high - low)), (ci, (low, high))
        poi = np.mean([(c > p) + 0.5 * (c == p) for c in finals[(env, "cascade_ppo_continuous")]
                       for p in finals[(env, "ppo_baseline")]])
        assert float(rows[(env, "Cascade")]["p_improvement"]) == pytest.approx(poi)
    assert float(rows[pooled]["p_improvement"]) == pytest.approx(
        np.mean([float(rows[(e, "Cascade")]["p_improvement"]) for e in ("Hopper-v4", "Walker2d-v4")]))
    normalized = np.concatenate([finals[(e, "cascade_ppo_continuous")] / finals[(e, "ppo_baseline")].mean()
                                 for e in ("Hopper-v4", "Walker2d-v4")])
    assert float(rows[pooled]["iqm"]) == pytest.approx(reference_iqm(normalized))
    assert float(rows[pooled]["iqm_ci_low"]) <= float(rows[pooled]["iqm"]) <= float(rows[pooled]["iqm_ci_high"])
    paths = learning_curves.main(learning_curves.Args(runs=(track,), out=str(tmp_path), name="two_envs"))
    curves = read_csv(tmp_path / "two_envs.csv")
    assert {(r["env"], r["seeds"]) for r in curves} == {("Hopper-v4", "10"), ("Walker2d-v4", "10")}


def test_fallback_figures_and_tables_match_logged_fallbacks(runs, tmp_path):
    paths = fallback.main(fallback.Args(runs=(runs["track"],), out=str(tmp_path)))
    assert_figures(paths, "fallback_product", "fallback_per_net")
    rows = read_csv(tmp_path / "fallback_tables.csv")
    value = {(r["quantity"], r["net"]): float(r["mean"]) for r in rows}
    assert {r["experiment"] for r in rows} == {"Cascade"}  # the PPO runs log no fallbacks and are left out
    lam = np.mean(last_values(runs["cascade"], "cascade/fallback/net_2"))
    spread = np.mean(last_values(runs["cascade"], "cascade/fallback_std/net_2"))
    product = np.mean(last_values(runs["cascade"], "cascade/fallback_product"))
    assert value[("fallback", "2")] == pytest.approx(lam, rel=1e-6)
    assert value[("fallback_std", "2")] == pytest.approx(spread, rel=1e-6)
    assert value[("fallback_product", "")] == pytest.approx(product, rel=1e-6)
    tables = (tmp_path / "fallback_tables.md").read_text()
    assert "Table 1" in tables and "Table 3" in tables and "| λ_2 |" in tables and f"{lam:.2f} ± " in tables


def test_member_returns_match_logged_returns(runs, tmp_path):
    paths = members.main(members.Args(runs=(runs["track"],), out=str(tmp_path)))
    assert_figures(paths, "members")
    rows = read_csv(tmp_path / "members.csv")
    assert [(r["iteration"], r["step"]) for r in rows] == [("1", "1024"), ("2", "2048")]
    logged = [read_scalars(d) for d in runs["cascade"]]
    for row in rows:
        step = int(row["step"])
        full = np.mean([dict(s["eval/episodic_return"])[step] for s in logged])
        bottom = np.mean([dict(s["members/return/net_1"])[step] for s in logged])
        assert float(row["full_stack"]) == pytest.approx(full, rel=1e-6)
        assert float(row["net_1"]) == pytest.approx(bottom, rel=1e-6)
    assert rows[0]["net_2"] == "" and float(rows[1]["net_2"]) == pytest.approx(
        np.mean([dict(s["members/return/net_2"])[2048] for s in logged]), rel=1e-6)


def test_final_fallbacks_average_the_last_stack_only(tmp_path, capsys):
    """A fault hunt: with a window reaching back before the top net was added, w₁ took in the product of the smaller
    stack (1.0 before net 2) while λ of the top net averaged fewer values, so w₁ was not the product of the λs and a
    run folder and its export disagreed. The window is cut to the top net's values, with a note."""
    import json

    sample = os.path.join(ROOT, "results", "sample")
    name = next(n for n in sorted(os.listdir(sample)) if "__cascade__" in n)
    one = tmp_path / "one"
    one.mkdir()
    shutil.copy(os.path.join(sample, name), one)
    data = json.load(open(one / name))
    tops = data["scalars"]["cascade/fallback/net_3"]["values"]
    products = data["scalars"]["cascade/fallback_product"]["values"]
    assert len(tops) == 2 and len(products) > 3  # (net 3 was added 2 evaluations before the end)
    capsys.readouterr()
    fallback.main(fallback.Args(runs=(str(one),), out=str(tmp_path / "out"), final_window=3))
    assert f"note: {name[:-5]}: its final fallbacks average its last 2 logged value(s), not 3" in capsys.readouterr().err
    rows = {(r["quantity"], r["net"]): float(r["mean"]) for r in read_csv(tmp_path / "out" / "fallback_tables.csv")}
    assert rows[("fallback_product", "")] == pytest.approx(np.mean(products[-2:]), rel=1e-9)
    assert rows[("fallback", "3")] == pytest.approx(np.mean(tops), rel=1e-9)
    assert rows[("fallback", "2")] == pytest.approx(np.mean(data["scalars"]["cascade/fallback/net_2"]["values"][-2:]))


def test_fallback_course_follows_the_saved_policy(runs, tmp_path):
    run_dir = runs["cascade"][0]
    paths = analyze.fallback_course(analyze.FallbackCourse(checkpoint=run_dir, out=str(tmp_path), seed=3))
    assert_figures(paths, "fallback_course")
    rows = read_csv(tmp_path / "fallback_course.csv")
    assert len(rows) >= 1 and all(0.0 < float(r["lambda_2"]) < 1.0 for r in rows)
    # first step, recomputed by hand: the reset observation, normalized with the saved statistics
    checkpoint = cpc.load_checkpoint(run_dir)
    actor = cpc.actor_from_checkpoint(checkpoint)
    env = analyze.make_env("Hopper-v4")
    obs, _ = env.reset(seed=3)
    with torch.no_grad():
        _, _, fallback_first, _ = actor(torch.as_tensor(cpc.normalize_obs(obs[None], checkpoint["obs_stats"])))
    assert float(rows[0]["lambda_2"]) == pytest.approx(float(fallback_first[0, 0]), rel=1e-6)


def test_plasticity_small(runs, tmp_path):
    run_dir = runs["cascade"][0]
    # the stack "after" is exactly the one training built at the start of iteration 2
    checkpoint = cpc.load_checkpoint(os.path.join(run_dir, "iteration_1.pt"))
    after = analyze.stack_after_adding(checkpoint).state_dict()
    assert after.keys() == runs["second_net"].keys()
    for key, value in runs["second_net"].items():
        torch.testing.assert_close(after[key], value, rtol=0, atol=0)

    result = analyze.plasticity(analyze.Plasticity(checkpoint=run_dir, out=str(tmp_path), updates=30, samples=2,
                                                   observations=40))
    assert (result["before"]["nets"], result["after"]["nets"]) == (1, 2)
    for which in ("before", "after"):
        r = result[which]
        assert np.all(np.isfinite(r["plasticity"])) and np.all((r["b"] > 0) & (r["b"] <= 1))
        assert np.all(r["final_loss"] < r["initial_loss"])  # the fit makes progress
        np.testing.assert_allclose(r["plasticity"], r["b"] - r["final_loss"])
    table = read_csv(tmp_path / "plasticity.csv")
    assert len(table) == 4 and float(table[0]["plasticity"]) == pytest.approx(result["before"]["plasticity"][0])


def test_table2_matches_logged_parameters_and_wall_time(runs, tmp_path):
    analyze.table2(analyze.Table2(runs=(runs["track"],), out=str(tmp_path)))
    rows = {r["experiment"]: r for r in read_csv(tmp_path / "table2.csv")}
    assert float(rows["PPO"]["parameters"]) == 10119  # Table 2 of the paper, Hopper PPO
    assert float(rows["Cascade"]["parameters"]) == read_scalars(runs["cascade"][0])["cascade/parameters"][-1][1]
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    seconds = []
    for d in runs["baseline"]:
        acc = EventAccumulator(d, size_guidance={"scalars": 0})
        acc.Reload()
        times = [e.wall_time for tag in acc.Tags()["scalars"] for e in acc.Scalars(tag)]
        seconds.append(max(times) - min(times))
    assert float(rows["PPO"]["seconds_mean"]) == pytest.approx(np.mean(seconds), rel=1e-6)
    assert "Parameters Cascade" in (tmp_path / "table2.md").read_text()


# ----------------------------------------------------------------------------------------------
# Bad input: one clear line naming what was looked for and what was found
# ----------------------------------------------------------------------------------------------
def error_of(call):
    with pytest.raises(SystemExit) as info:
        call()
    message = str(info.value)
    assert message.startswith("error: ") and "\n" not in message
    return message


def test_no_matching_runs(runs, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    message = error_of(lambda: learning_curves.main(learning_curves.Args(runs=(str(empty),), out=str(tmp_path))))
    assert "no run folders" in message and str(empty) in message
    message = error_of(lambda: learning_curves.main(learning_curves.Args(
        runs=(runs["track"],), experiments=("cascade_freeze",), out=str(tmp_path))))
    assert "cascade_freeze" in message and "Hopper-v4/cascade_ppo_continuous (2 runs)" in message
    assert "Hopper-v4/ppo_baseline (2 runs)" in message
    message = error_of(lambda: learning_curves.main(learning_curves.Args(runs=(str(tmp_path / "nope"),))))
    assert "does not exist" in message
    # a file (a fault hunt: "does not exist"): an exported run file is that run; another file is refused as one
    other = tmp_path / "notes.txt"
    other.write_text("x")
    message = error_of(lambda: learning_curves.main(learning_curves.Args(runs=(str(other),), out=str(tmp_path))))
    assert f"--runs '{other}' is a file, not a runs folder" in message, message
    sample = os.path.join(ROOT, "results", "sample")
    files = tuple(os.path.join(sample, name) for name in sorted(os.listdir(sample)))
    paths = learning_curves.main(learning_curves.Args(runs=files, out=str(tmp_path / "files")))
    folder = learning_curves.main(learning_curves.Args(runs=(sample,), out=str(tmp_path / "folder")))
    assert [os.path.basename(p) for p in paths] == [os.path.basename(p) for p in folder]
    csv = next(os.path.basename(p) for p in paths if p.endswith(".csv"))
    assert read_csv(tmp_path / "files" / csv) == read_csv(tmp_path / "folder" / csv)


def test_a_bad_mplbackend_does_not_stop_the_plots(tmp_path):
    """A fault hunt: MPLBACKEND=bogus in the environment failed matplotlib's import with a traceback; the plots draw
    on Agg whatever it names."""
    proc = subprocess.run([sys.executable, os.path.join(ROOT, "plots", "learning_curves.py"), "--runs",
                           os.path.join(ROOT, "results", "sample"), "--out", str(tmp_path)], capture_output=True,
                          text=True, env={**os.environ, "MPLBACKEND": "bogus"}, timeout=300)
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert any(name.endswith(".png") for name in os.listdir(tmp_path))


def test_runs_of_another_env_in_a_panel(runs, tmp_path):
    mixed = tmp_path / "mixed"
    shutil.copytree(runs["track"], mixed)
    # a Hopper run copied under a Walker2d name would be drawn in the Walker2d panel
    name = os.path.basename(runs["cascade"][0]).replace("Hopper-v4", "Walker2d-v4")
    shutil.copytree(runs["cascade"][0], mixed / name)
    message = error_of(lambda: learning_curves.main(learning_curves.Args(runs=(str(mixed),), out=str(tmp_path))))
    assert "env_id=Walker2d-v4" in message and "env_id=Hopper-v4" in message and name in message


def test_missing_scalar(runs, tmp_path):
    message = error_of(lambda: learning_curves.main(learning_curves.Args(
        runs=(runs["track"],), scalar="eval/success_rate", out=str(tmp_path))))
    assert "'eval/success_rate'" in message and "eval/episodic_return" in message and "ppo_baseline" in message
    message = error_of(lambda: fallback.main(fallback.Args(runs=(runs["track"],), experiments=("ppo_baseline",),
                                                           out=str(tmp_path))))
    assert "'cascade/fallback_product'" in message and "charts/parameters" in message
    message = error_of(lambda: analyze.fallback_course(analyze.FallbackCourse(
        checkpoint=os.path.join(runs["cascade"][0], "iteration_1.pt"), out=str(tmp_path))))
    assert "1 base net" in message


def test_command_line(runs, tmp_path):
    """As a user runs it, from another folder: PNG/PDF written; bad input exits non-zero with one line."""
    script = os.path.join(ROOT, "plots", "learning_curves.py")
    ok = subprocess.run([sys.executable, script, "--runs", runs["track"], "--out", str(tmp_path / "cli")],
                        capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert ok.returncode == 0, ok.stderr
    assert (tmp_path / "cli" / "learning_curves.png").stat().st_size > 5000
    bad = subprocess.run([sys.executable, script, "--runs", runs["track"], "--envs", "Ant-v4"],
                         capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert bad.returncode != 0 and bad.stderr.strip().count("\n") == 0
    assert bad.stderr.startswith("error: --envs Ant-v4: no runs") and "Hopper-v4" in bad.stderr


def test_each_name_and_folder_a_command_line_gives_is_checked(runs, tmp_path):
    """Audit: a typo in one of several names (--experiments, --envs, --labels) was left out of the figure silently,
    exit 0; an --out that is a file or a --name with a folder was a traceback."""
    track, both = (runs["track"],), ("cascade_ppo_continuous", "ppo_baseline")
    for args, flag in [(dict(experiments=("cascade_ppo_continuous", "cascade_ppo_continous")), "--experiments"),
                       (dict(envs=("Hopper-v4", "Ant-v4")), "--envs"),
                       (dict(labels=("cascade_ppo_continous=Cascade",)), "--labels")]:
        message = error_of(lambda args=args: common.check_cli(learning_curves.Args(runs=track, out=str(tmp_path), **args)))
        assert message.startswith(f"error: {flag} ") and "no runs" in message, message
    assert "cascade_ppo_continuous" in error_of(lambda: common.check_cli(final_performance.Args(
        runs=track, experiments=("cascade_ppo_continous",), out=str(tmp_path))))  # the close match is named
    common.check_cli(learning_curves.Args(runs=track, experiments=both, envs=("Hopper-v4",), out=str(tmp_path)))
    # a baseline named explicitly must have runs (its experiment or display label); the default may be absent
    assert error_of(lambda: common.check_cli(final_performance.Args(runs=track, baseline="ppo_basline"))).startswith(
        "error: --baseline ppo_basline: no runs")
    for baseline in ("ppo_baseline", "PPO"):
        common.check_cli(final_performance.Args(runs=track, baseline=baseline))
    assert "--nets 9: the runs' nets with a fallback are 2" in error_of(lambda: fallback.main(fallback.Args(
        runs=track, nets=(9,), out=str(tmp_path / "fb"))))
    # (a fault hunt: a --split-by typo split nothing and --columns 0 drew one column, silently)
    message = error_of(lambda: learning_curves.main(learning_curves.Args(runs=track, split_by=("fallback-nit",),
                                                                         out=str(tmp_path / "sb"))))
    assert message.startswith("error: --split-by fallback_nit: no run records that setting (they record: "
                              "fallback_init"), message
    learning_curves.main(learning_curves.Args(runs=track, split_by=("fallback-init",), out=str(tmp_path / "sb")))
    assert error_of(lambda: common.check_cli(learning_curves.Args(runs=track, columns=0))) == \
        "error: --columns must be at least 1 (got 0)"
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    for out in (a_file, a_file / "below"):
        assert "is a file, not a folder" in error_of(lambda out=out: common.check_cli(learning_curves.Args(
            runs=track, out=str(out))))
    # a folder where nothing can be made, even by root, whom os.access lets write anywhere (a fresh-user hunt: a
    # traceback from os.makedirs after the figures were computed)
    if sys.platform.startswith("linux"):
        message = error_of(lambda: common.check_cli(learning_curves.Args(runs=track, out="/proc/cascade_figures")))
        assert message.startswith("error: --out /proc/cascade_figures: /proc cannot be written (") and \
            "pass a folder you can write to" in message, message
    for name in ("sub/x", ""):
        assert "--name" in error_of(lambda name=name: common.check_cli(learning_curves.Args(runs=track, name=name)))
    script = os.path.join(ROOT, "plots", "fallback.py")
    bad = subprocess.run([sys.executable, script, "--runs", runs["track"], "--experiments", "cascade_ppo_continuous",
                          "cascade_fb005", "--out", str(tmp_path / "x")], capture_output=True, text=True, timeout=120)
    assert bad.returncode != 0 and bad.stderr.startswith("error: --experiments cascade_fb005: no runs"), bad.stderr
    assert not (tmp_path / "x").exists()


def test_members_with_a_seed_that_has_fewer_nets(runs, tmp_path):
    """Audit: a seed still running (or of a smaller n) has no member returns of the later nets: a KeyError."""
    import json

    from plots import export_results

    exported = tmp_path / "exported"
    export_results.main(export_results.Args(runs=[runs["track"]], out=str(exported), commit="test"))

    name = os.path.basename(runs["cascade"][1]) + ".json"
    data = json.load(open(exported / name))
    del data["scalars"]["members/return/net_2"]
    json.dump(data, open(exported / name, "w"))
    members.main(members.Args(runs=(str(exported),), out=str(tmp_path / "out")))
    rows = read_csv(tmp_path / "out" / "members.csv")
    seed_1 = dict(read_scalars(runs["cascade"][0])["members/return/net_2"])[2048]
    assert float(rows[1]["net_2"]) == pytest.approx(seed_1, rel=1e-6)  # the one seed that has it
    # a seed one iteration behind (the others share one iteration end with it): still drawn, one point (review)
    for key in ("members/return/net_1", "cascade/size"):
        series = data["scalars"][key]
        keep = [i for i, step in enumerate(series["steps"]) if step <= 1024]
        data["scalars"][key] = {field: [values[i] for i in keep] for field, values in series.items()}
    json.dump(data, open(exported / name, "w"))
    members.main(members.Args(runs=(str(exported),), out=str(tmp_path / "out")))


def test_analyze_names_what_a_wrong_checkpoint_is_and_advises_no_resume(runs, tmp_path):
    """Audit: another script's checkpoint was "not a cascade_ppo_continuous checkpoint" with no word of what it was,
    and a corrupt checkpoint.pt advised `analyze.py --resume`, a flag analyze.py does not have."""
    import cascade_ppo_discrete as cpd

    discrete = cpd.train(cpd.Args(env_id="CartPole-v1", n=1, k=256, num_envs=1, num_steps=128, eval_every=0,
                                  quiet=True, track_dir=str(tmp_path / "discrete")))["run_dir"]
    message = error_of(lambda: analyze.fallback_course(analyze.FallbackCourse(checkpoint=discrete, out=str(tmp_path))))
    assert "is not a cascade_ppo_continuous checkpoint (it is a cascade_ppo_discrete checkpoint)" in message, message
    broken = tmp_path / os.path.basename(runs["cascade"][0])
    shutil.copytree(runs["cascade"][0], broken)
    (broken / "checkpoint.pt").write_bytes(b"not a checkpoint")
    proc = subprocess.run([sys.executable, os.path.join(ROOT, "plots", "analyze.py"), "fallback-course",
                           "--checkpoint", str(broken), "--out", str(tmp_path / "out")],
                          capture_output=True, text=True, timeout=120)
    line = proc.stderr.strip()
    assert proc.returncode != 0 and "cannot read checkpoint" in line and "--resume" not in line, line
    assert line.endswith(f"{broken / 'iteration_2.pt'} (the end of iteration 2): pass that with --checkpoint"), line
    # the advice follows from the caller, not from the program's name: the same call made from another program
    in_process = error_of(lambda: analyze.plasticity(analyze.Plasticity(checkpoint=str(broken / "checkpoint.pt"),
                                                                       out=str(tmp_path / "out"))))
    assert in_process.endswith("(the end of iteration 2): pass that with --checkpoint"), in_process


def test_reproduce_writes_nothing_without_the_standard_runs(tmp_path):
    """Audit: with no Cascade runs it wrote Fig. 2 and the final performance, then stopped: a half-rebuilt folder."""
    from plots import reproduce

    only_ppo = tmp_path / "only_ppo"
    only_ppo.mkdir()
    sample = os.path.join(ROOT, "results", "sample")
    for name in os.listdir(sample):
        if "__ppo__" in name:
            shutil.copy(os.path.join(sample, name), only_ppo)
    message = error_of(lambda: reproduce.main(reproduce.Args(runs=str(only_ppo), out=str(tmp_path / "out"), reps=50)))
    assert "no exported runs of cascade" in message and not (tmp_path / "out").exists()


def test_reproduce_draws_the_other_scripts_figures_without_fig2_runs(tmp_path):
    """A fault hunt: a folder of Fig. 14-16 runs only (the other scripts' sweeps) was refused for want of Fig. 2's
    standard runs, which none of those figures draws. Now they are drawn, and summary.md says Fig. 2 is not there;
    an ablation drawn beside standard Cascade still needs those runs, and a folder of no known experiment is refused."""
    import json

    from plots import reproduce

    sample, runs = os.path.join(ROOT, "results", "sample"), tmp_path / "fig14"
    runs.mkdir()
    scores = {}
    for name in sorted(os.listdir(sample)):
        data = json.load(open(os.path.join(sample, name)))
        exp, seed = data["hparams"]["exp_name"], data["hparams"]["seed"]
        if seed != "1":
            continue
        new_exp = {"cascade": "cascade_sac", "ppo": "sac"}[exp]
        data["hparams"]["exp_name"] = new_exp
        data["name"] = data["name"].replace(f"__{exp}__", f"__{new_exp}__")
        scores[new_exp] = np.mean(data["scalars"]["eval/episodic_return"]["values"][-3:])
        json.dump(data, open(runs / f"{data['name']}.json", "w"))
    paths = reproduce.main(reproduce.Args(runs=str(runs), out=str(tmp_path / "out"), reps=20))
    assert {os.path.basename(p) for p in paths} >= {"fig14_sac.png", "summary.md"}
    assert not any(os.path.basename(p).startswith(("fig2", "final_performance")) for p in paths), paths
    summary = open(tmp_path / "out" / "summary.md").read()
    assert "No runs of Fig. 2 (standard Cascade and PPO) here" in summary, summary
    row = next(line for line in summary.splitlines() if line.startswith("| Hopper-v4 |"))
    assert f"{scores['cascade_sac']:.0f} (seeds 1)" in row and f"{scores['sac']:.0f} (seeds 1)" in row, row
    frozen = tmp_path / "frozen"  # Fig. 4 compares with standard Cascade: still refused without it
    frozen.mkdir()
    data = json.load(open(runs / os.listdir(runs)[0]))
    data["hparams"].update(exp_name="cascade_frozen", env_id="Ant-v4")
    data["name"] = "Ant-v4__cascade_frozen__1__1"
    json.dump(data, open(frozen / f"{data['name']}.json", "w"))
    message = error_of(lambda: reproduce.main(reproduce.Args(runs=str(frozen), out=str(tmp_path / "o2"), reps=20)))
    assert "no exported runs of cascade" in message and not (tmp_path / "o2").exists(), message
    os.remove(frozen / f"{data['name']}.json")
    data["hparams"]["exp_name"], data["name"] = "mine", "Ant-v4__mine__1__1"
    json.dump(data, open(frozen / f"{data['name']}.json", "w"))
    message = error_of(lambda: reproduce.main(reproduce.Args(runs=str(frozen), out=str(tmp_path / "o3"), reps=20)))
    assert "has runs of none of the paper's experiments" in message and not (tmp_path / "o3").exists(), message


def test_reproduce_checks_its_numbers_before_writing(tmp_path):
    """Audit: --final-window 0 (or --reps 0) rewrote Fig. 2's curves, then stopped at the final scores."""
    from plots import reproduce

    sample = os.path.join(ROOT, "results", "sample")
    for bad in ({"final_window": 0}, {"reps": 0}):
        message = error_of(lambda bad=bad: reproduce.main(reproduce.Args(runs=sample, out=str(tmp_path / "out"), **bad)))
        assert message == "error: --final-window and --reps must be at least 1", message
        assert not (tmp_path / "out").exists()


def test_reproduce_names_an_earlier_builds_files_and_reads_every_run_first(tmp_path, capsys):
    """A fault hunt: rebuilt into a folder of an earlier build (results/figures) from other runs, the figures it did
    not redraw stayed beside the new ones, unmentioned; a damaged run file stopped it after half the figures."""
    from plots import reproduce

    sample, out = os.path.join(ROOT, "results", "sample"), tmp_path / "out"
    reproduce.main(reproduce.Args(runs=sample, out=str(out), reps=20))
    capsys.readouterr()
    reproduce.main(reproduce.Args(runs=sample, out=str(out), reps=20))  # the same build again: nothing left over
    assert "not from these runs" not in capsys.readouterr().err
    (out / "fig14_sac.png").write_bytes(b"an earlier build's figure")
    reproduce.main(reproduce.Args(runs=sample, out=str(out), reps=20))
    err = capsys.readouterr().err
    assert f"note: 1 file(s) in {out} are not from these runs" in err and "fig14_sac.png" in err, err
    assert (out / "fig14_sac.png").exists()  # said, not removed
    damaged = tmp_path / "damaged"
    shutil.copytree(sample, damaged)
    last = sorted(os.listdir(damaged))[-1]
    text = (damaged / last).read_text()
    (damaged / last).write_text(text[: len(text) // 2])
    message = error_of(lambda: reproduce.main(reproduce.Args(runs=str(damaged), out=str(tmp_path / "new"), reps=20)))
    assert last in message and not (tmp_path / "new").exists(), message


def test_reproduction_rebuilds_from_the_committed_sample(tmp_path):
    """plots/reproduce.py rebuilds every figure and table of results/ from exported run files alone
    (results/sample: two tiny Cascade and PPO runs per seed on Hopper-v4, exported by plots/export_results.py)."""
    import json

    from plots import reproduce

    sample = os.path.join(ROOT, "results", "sample")
    paths = reproduce.main(reproduce.Args(runs=sample, out=str(tmp_path), reps=200))
    names = {os.path.basename(p) for p in paths}
    for expected in ("fig2_learning_curves.png", "final_performance.md", "fallback_tables.md", "members.md",
                     "runtime.md", "summary.md"):
        assert expected in names, names
    # the summary's scores are the mean of each run's last 3 evaluations, averaged over seeds
    scores = {"cascade": [], "ppo": []}
    for name in sorted(os.listdir(sample)):
        data = json.load(open(os.path.join(sample, name)))
        scores[data["hparams"]["exp_name"]].append(np.mean(data["scalars"]["eval/episodic_return"]["values"][-3:]))
        assert data["command"] and data["commit"] and data["seconds"] > 0
    summary = open(tmp_path / "summary.md").read()
    # it names the runs it was built from, not ours (a fault hunt: "our runs, results/per_run" whatever --runs)
    assert summary.startswith(f"# Reproduction of the paper's Fig. 2 (the runs of {os.path.normpath(sample)})")
    assert "results/per_run" not in summary and "2 cores" not in summary
    # the evaluation protocol it states is the runs' own (it said "every 50k steps, 10 episodes" whatever they did)
    logged = {(data["hparams"]["eval_every"], data["hparams"]["eval_episodes"])
              for data in (json.load(open(os.path.join(sample, name))) for name in os.listdir(sample))}
    assert len(logged) == 1 and logged != {("50000", "10")}, logged
    every, episodes = logged.pop()
    assert f"last 3 evaluations (every {common.format_steps(int(every))} steps, {episodes} episodes each" in summary
    row = next(line for line in summary.splitlines() if line.startswith("| Hopper-v4 |"))
    assert f"{np.mean(scores['cascade']):.0f} ± " in row and f"{np.mean(scores['ppo']):.0f} ± " in row, row
    better = reference_improvement(np.array(scores["cascade"]), np.array(scores["ppo"]))
    assert better != 0.5 and f"| {better:.2f} |" in row, row  # P(Cascade > PPO), not P(PPO > Cascade)
    # final_performance's scores too: each run's last 3 evaluations (the sample's last evaluation differs)
    rows = {r["experiment"]: r for r in read_csv(tmp_path / "final_performance.csv")}
    assert float(rows["Cascade"]["mean"]) == pytest.approx(np.mean(scores["cascade"]), rel=1e-6)
    assert float(rows["PPO"]["mean"]) == pytest.approx(np.mean(scores["ppo"]), rel=1e-6)


def test_exported_runs_hold_what_the_figures_read(runs, tmp_path, capsys):
    """plots/export_results.py: every evaluation, member return and fallback std in full; the per-update scalars
    the figures read as the last value logged at or before each evaluation step; the settings, the commit and
    the training time. The plots read the exported files as they read the run folders."""
    import json

    from plots import export_results

    out = tmp_path / "per_run"
    written = export_results.main(export_results.Args(runs=[runs["track"]], out=str(out), commit="0123abc"))
    run_dirs = runs["cascade"] + runs["baseline"]
    assert sorted(written) == sorted(str(out / f"{os.path.basename(d)}.json") for d in run_dirs)
    for run_dir in run_dirs:
        data = json.load(open(out / f"{os.path.basename(run_dir)}.json"))
        assert (data["commit"], data["final_step"], data["hparams"]["seed"]) == ("0123abc", 2048, data["name"].split("__")[2])
        elapsed = torch.load(os.path.join(run_dir, "checkpoint.pt"), weights_only=False)["elapsed"]
        assert data["seconds"] == pytest.approx(elapsed)
        logged = read_scalars(run_dir)
        evaluations = [step for step, _ in logged["eval/episodic_return"]]
        for tag, entries in logged.items():
            if tag.startswith(("eval/", "members/", "cascade/fallback_std/")):
                expected = entries
            elif tag.startswith(("cascade/fallback/", "cascade/contribution/", "cascade/fallback_product",
                                 "cascade/size", "cascade/parameters", "charts/parameters", "charts/SPS")):
                expected = []
                for at in evaluations:
                    before = [value for step, value in entries if step <= at]
                    if before:
                        expected.append((at, before[-1]))
                assert len(expected) > 1 and any(step in evaluations for step, _ in entries), tag
            else:
                assert tag not in data["scalars"], tag
                continue
            exported = data["scalars"][tag]
            assert exported["steps"] == [step for step, _ in expected], tag
            assert exported["values"] == pytest.approx([value for _, value in expected], rel=1e-6), tag
    for script, extra in ((learning_curves, {}), (final_performance, {"reps": 100})):  # the files read as the folders
        for source, name in ((runs["track"], "folders"), (str(out), "files")):
            script.main(script.Args(runs=(source,), out=str(tmp_path / name), **extra))
        table = os.path.basename(script.__file__).replace(".py", ".csv")
        assert read_csv(tmp_path / "files" / table) == read_csv(tmp_path / "folders" / table), table
    # existing files are kept (--overwrite rewrites them); an unfinished run is left out (--allow-incomplete)
    assert export_results.main(export_results.Args(runs=[runs["track"]], out=str(out))) == []
    assert len(export_results.main(export_results.Args(runs=[runs["track"]], out=str(out), overwrite=True))) == 4
    killed = write_fake_run(tmp_path / "killed", "Hopper-v4__ppo_baseline__3__1700000000", [0, 500_000],
                            hparams={"num_envs": 1, "num_steps": 2048, "total_timesteps": 1_000_000, "seed": 3})
    args = export_results.Args(runs=[os.path.dirname(killed)], out=str(tmp_path / "killed_out"))
    capsys.readouterr()
    assert "nothing exported" in error_of(lambda: export_results.main(args))  # (it exited 0 with the note alone)
    assert "evaluated up to step 500,000 of 999,424 (unfinished)" in capsys.readouterr().err
    # ... a SAC or DDPG run too (they log no rollout size: an unfinished one was exported as finished, a fault hunt)
    for label, finished in (("cascade_sac", 1_000_000), ("cascade_ddpg", 2_000_000)):
        partial = write_fake_run(tmp_path / "offpolicy", f"Hopper-v4__{label}__1__1700000000", [0, 1_000_000, finished],
                                 hparams={"n": 4, "k": 500_000, "learning_starts": 5000, "seed": 1})
        export = export_results.Args(runs=[partial], out=str(tmp_path / f"{label}_out"))
        if finished < 2_000_000:
            assert "nothing exported" in error_of(lambda export=export: export_results.main(export))
            assert "evaluated up to step 1,000,000 of 2,000,000 (unfinished)" in capsys.readouterr().err
        else:
            assert len(export_results.main(export)) == 1 and "unfinished" not in capsys.readouterr().err
    # two folders of one run name would write one file, the second over the first: refused before anything is written
    twin = write_fake_run(tmp_path / "twins" / "a", "Hopper-v4__ppo_baseline__3__1700000000", [0, 500_000])
    write_fake_run(tmp_path / "twins" / "b", os.path.basename(twin), [0, 500_000])
    message = error_of(lambda: export_results.main(export_results.Args(runs=[str(tmp_path / "twins")],
                                                                       out=str(tmp_path / "twins_out"))))
    assert "two run folders are named Hopper-v4__ppo_baseline__3__1700000000" in message
    assert not (tmp_path / "twins_out").exists()
    assert len(export_results.main(dataclasses.replace(args, allow_incomplete=True))) == 1
    # one run folder given itself, with a trailing slash (as a shell completes it), is that run; a folder
    # with no run in it is an error, not a silent nothing; a file already there is named when skipped
    one = runs["baseline"][0] + os.sep
    written = export_results.main(export_results.Args(runs=[one], out=str(tmp_path / "one")))
    assert written == [str(tmp_path / "one" / f"{os.path.basename(runs['baseline'][0])}.json")]
    capsys.readouterr()
    assert export_results.main(export_results.Args(runs=[one], out=str(tmp_path / "one"))) == []
    assert "exists (--overwrite replaces it)" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit, match="no run folders"):
        export_results.main(export_results.Args(runs=[str(tmp_path / "empty")], out=str(tmp_path / "none")))


def test_ablation_figures_come_from_the_ablation_runs_only(tmp_path, capsys):
    """An ablation's figure and summary section appear once a variant's runs are exported, with its scores, on
    Ant-v4 and Walker2d-v4 (Fig. 8: on the envs of its runs); Fig. 2 keeps drawing standard Cascade and PPO only,
    though the ablation runs share the folder."""
    import json

    from plots import reproduce

    sample, runs = os.path.join(ROOT, "results", "sample"), tmp_path / "per_run"
    runs.mkdir()
    scores = {}
    for name in sorted(os.listdir(sample)):
        data = json.load(open(os.path.join(sample, name)))
        shutil.copy(os.path.join(sample, name), runs / name)
        exp, seed = data["hparams"]["exp_name"], data["hparams"]["seed"]
        # the same runs as Ant-v4 runs, and seed 1 of Cascade as the frozen variant with halved returns
        # and as the fallback-init 0.9 variant with its fallback product scaled by 1.5 (Fig. 6)
        variants = [(exp, 1.0)] + ([("cascade_frozen", 0.5), ("cascade_fallback0.9", 1.0)]
                                   if (exp, seed) == ("cascade", "1") else [])
        for new_exp, factor in variants:
            run = json.loads(json.dumps(data))
            run["hparams"].update(env_id="Ant-v4", exp_name=new_exp)
            run["name"] = run["name"].replace("Hopper-v4", "Ant-v4").replace(f"__{exp}__", f"__{new_exp}__")
            returns = run["scalars"]["eval/episodic_return"]
            returns["values"] = [v * factor for v in returns["values"]]
            scores.setdefault(new_exp, []).append(np.mean(returns["values"][-3:]))
            if new_exp == "cascade_fallback0.9":
                product = run["scalars"]["cascade/fallback_product"]
                product["values"] = [v * 1.5 for v in product["values"]]
                scores["product0.9"] = product["values"][-2:]  # (its net 3 logged 2 values: the last stack)
            json.dump(run, open(runs / f"{run['name']}.json", "w"))
        if seed == "1":  # Fig. 16's pair (`--preset discrete`) on Walker2d-v4 alone, returns scaled by 3
            run = json.loads(json.dumps(data))
            new_exp = f"{exp}_discrete"
            run["hparams"].update(env_id="Walker2d-v4", exp_name=new_exp)
            run["name"] = run["name"].replace("Hopper-v4", "Walker2d-v4").replace(f"__{exp}__", f"__{new_exp}__")
            returns = run["scalars"]["eval/episodic_return"]
            returns["values"] = [v * 3 for v in returns["values"]]
            scores[new_exp] = np.mean(returns["values"][-3:])
            json.dump(run, open(runs / f"{run['name']}.json", "w"))
        if (exp, seed) == ("cascade", "1"):  # a Fig. 8 run (`--preset tiny`) on Hopper-v4, an env of no other ablation
            run = json.loads(json.dumps(data))
            run["hparams"]["exp_name"] = "cascade_tiny_k1M"
            run["name"] = run["name"].replace("__cascade__", "__cascade_tiny_k1M__")
            json.dump(run, open(runs / f"{run['name']}.json", "w"))
            run["hparams"]["exp_name"] = "cascade_frozen"  # and a Fig. 4 run on Hopper-v4 (sweep.py's default env)
            run["name"] = run["name"].replace("__cascade_tiny_k1M__", "__cascade_frozen__")
            json.dump(run, open(runs / f"{run['name']}.json", "w"))
    capsys.readouterr()
    paths = reproduce.main(reproduce.Args(runs=str(runs), out=str(tmp_path / "out"), reps=100))
    err = capsys.readouterr().err  # not drawn (the paper's envs only), and said so
    assert "note: Fig. 4: the runs of cascade_frozen on Hopper-v4 are not drawn (the paper draws it on Ant-v4, " \
        "Walker2d-v4 only)" in err, err
    names = {os.path.basename(p) for p in paths}
    assert {"fig4_frozen.png", "fig11_fallback_init.png", "fig6_fig7_fallback_init_product.png",
            "fig6_fig7_fallback_init_per_net.png"} <= names, names
    assert not any(n.startswith(("fig3_", "fig5_", "fig10_", "fig12_", "fig13_")) for n in names), names
    table1 = read_csv(tmp_path / "out" / "fig6_fig7_fallback_init_tables.csv")
    products = {row["experiment"]: float(row["mean"]) for row in table1 if row["quantity"] == "fallback_product"}
    assert products.keys() == {"0.5 (standard)", "0.9"}, products  # Fig. 6 draws the fallback-init runs only
    assert products["0.9"] == pytest.approx(np.mean(scores["product0.9"]), rel=1e-6), products
    summary = open(tmp_path / "out" / "summary.md").read()
    section = summary[summary.index("## Fig. 4"):]
    row = next(line for line in section.splitlines() if line.startswith("| Ant-v4 |"))
    assert f"{np.mean(scores['cascade']):.0f} ± " in row and f"{scores['cascade_frozen'][0]:.0f} (seeds 1)" in row, row
    assert "severely worsens" in section
    tiny = summary[summary.index("## Fig. 8"):]
    assert "| Hopper-v4 |" in tiny and "| Ant-v4 |" not in tiny and "fig8_tiny.png" in names, tiny
    discrete = summary[summary.index("## Fig. 16"):]
    discrete = discrete[: discrete.index("Paper:")]
    row = next(line for line in discrete.splitlines() if line.startswith("| Walker2d-v4 |"))
    assert f"{scores['cascade_discrete']:.0f} (seeds 1)" in row and f"{scores['ppo_discrete']:.0f} (seeds 1)" in row
    assert "| Hopper-v4 |" not in discrete and "fig16_discrete.png" in names, discrete
    assert "## Fig. 14" not in summary and not any(n.startswith(("fig14", "fig15")) for n in names)
    fig2 = next(line for line in summary.splitlines() if line.startswith("| Ant-v4 |"))  # Fig. 2's table comes first
    assert f"{np.mean(scores['cascade']):.0f} ± " in fig2 and "(n=2)" in fig2, fig2
    curves = open(tmp_path / "out" / "fig2_learning_curves.csv").read()
    assert "frozen" not in curves


def write_fake_run(root, name, steps, value=1.0, hparams=None):
    """A run folder with `eval/episodic_return` logged at `steps` (TensorBoard's own writer), and `hparams` as
    the scripts log their settings."""
    from torch.utils.tensorboard import SummaryWriter

    writer = SummaryWriter(os.path.join(root, name))
    if hparams:
        writer.add_text("hyperparameters",
                        "|param|value|\n|-|-|\n" + "\n".join(f"|{key}|{setting}|" for key, setting in hparams.items()))
    for step in steps:
        writer.add_scalar("eval/episodic_return", value, step)
    writer.close()
    return os.path.join(root, name)


def test_damaged_and_truncated_runs_are_named_and_kept_out_of_final_scores(tmp_path, capsys):
    from plots import final_performance

    root = tmp_path / "runs"
    for seed, value in ((1, 100.0), (2, 200.0)):
        write_fake_run(root, f"Hopper-v4__ppo_baseline__{seed}__1700000000", [0, 4096, 8192], value)
    truncated = write_fake_run(root, "Hopper-v4__ppo_baseline__3__1700000000", [0, 2048], 5000.0)
    damaged = root / "Hopper-v4__ppo_baseline__4__1700000000"
    damaged.mkdir()
    (damaged / "events.out.tfevents.1700000000.host.1.0").write_bytes(b"\x00garbage, not a record")
    args = dict(runs=(str(root),), out=str(tmp_path / "out"), baseline="ppo_baseline", reps=50)
    final_performance.main(final_performance.Args(**args))
    err = capsys.readouterr().err
    assert str(damaged) in err and "no scalars" in err, err
    assert truncated in err and "stops at step 2,048" in err and "left out of the final scores" in err, err
    rows = read_csv(tmp_path / "out" / "final_performance.csv")
    assert [int(r["seeds"]) for r in rows if r["env"] == "Hopper-v4"] == [2], rows
    final_performance.main(final_performance.Args(**args, allow_incomplete=True))
    rows = read_csv(tmp_path / "out" / "final_performance.csv")
    assert [int(r["seeds"]) for r in rows if r["env"] == "Hopper-v4"] == [3], rows


def test_a_curve_whose_seeds_share_one_step_is_an_error(tmp_path):
    """Audit: a seed that had only just started (or one evaluated at other steps) left the group's curve a single
    point at step 0: the figure was drawn empty and the command exited 0."""
    root = tmp_path / "runs"
    for seed in (1, 2):
        write_fake_run(root, f"Hopper-v4__ppo_baseline__{seed}__1700000000", [0, 4096, 8192], 100.0 * seed)
    write_fake_run(root, "Hopper-v4__ppo_baseline__3__1700000000", [0], 5.0)
    message = error_of(lambda: learning_curves.main(learning_curves.Args(runs=(str(root),), out=str(tmp_path))))
    assert "share only step 0 of 'eval/episodic_return'" in message, message
    assert "Hopper-v4__ppo_baseline__3__1700000000 stops at step 0" in message, message
    (root / "Hopper-v4__ppo_baseline__3__1700000000").rename(tmp_path / "set_aside")
    paths = learning_curves.main(learning_curves.Args(runs=(str(root),), out=str(tmp_path)))
    rows = read_csv(next(p for p in paths if p.endswith(".csv")))
    assert sorted(int(r["step"]) for r in rows) == [0, 4096, 8192], rows


def test_final_scores_need_the_window_and_say_when_budgets_differ(tmp_path, capsys):
    """Audit: --final-window longer than the runs silently scored the mean of the whole run, and an experiment at
    8k steps was compared with one at 80k without a word."""
    root = tmp_path / "runs"
    write_fake_run(root, "Hopper-v4__ppo_baseline__1__1700000000", [0, 4096, 8192], 100.0)
    write_fake_run(root, "Hopper-v4__cascade__1__1700000000", range(0, 81920 + 1, 4096), 300.0)
    args = dict(runs=(str(root),), out=str(tmp_path / "out"), baseline="ppo_baseline", reps=50)
    message = error_of(lambda: final_performance.main(final_performance.Args(**args, final_window=4)))
    assert message.endswith("--final-window 4: Hopper-v4__ppo_baseline__1__1700000000 logs only 3 values of "
                            "'eval/episodic_return'; pass at most 3"), message
    capsys.readouterr()
    final_performance.main(final_performance.Args(**args, final_window=3))
    err = capsys.readouterr().err
    assert "on Hopper-v4 the experiments end at different steps (PPO: 8,192, cascade: 81,920)" in err, err
    shutil.rmtree(root / "Hopper-v4__ppo_baseline__1__1700000000")
    write_fake_run(root, "Hopper-v4__ppo_baseline__1__1700000000", range(0, 79872 + 1, 4096), 100.0)  # a rollout less
    final_performance.main(final_performance.Args(**args, final_window=3))
    assert "different steps" not in capsys.readouterr().err


def test_analyze_refuses_a_bad_learning_rate_and_names_n1_runs(runs, tmp_path):
    """Audit: plasticity --learning-rate -1 was a traceback deep in Adam, and fallback-course on a run of one net
    advised passing "a later iteration_<i>.pt", which such a run never writes."""
    message = error_of(lambda: analyze.plasticity(analyze.Plasticity(checkpoint=runs["cascade"][0], out=str(tmp_path),
                                                                     learning_rate=-1.0)))
    assert "--learning-rate -1.0: Adam's learning rate must be positive" in message, message
    single = cpc.train(cpc.Args(seed=1, n=1, k=512, track_dir=str(tmp_path / "single"), **TINY))["run_dir"]
    message = error_of(lambda: analyze.fallback_course(analyze.FallbackCourse(checkpoint=single, out=str(tmp_path))))
    assert message.endswith("holds 1 base net, which has no fallback; its run has no other (--n 1): pass a "
                            "checkpoint of a run with --n 2 or more"), message
    first = os.path.join(runs["cascade"][0], "iteration_1.pt")  # a run of two nets: its later file is the advice
    message = error_of(lambda: analyze.fallback_course(analyze.FallbackCourse(checkpoint=first, out=str(tmp_path))))
    assert message.endswith("pass a later iteration_<i>.pt or the run's checkpoint.pt"), message


@pytest.mark.parametrize("settings", [dict(total_timesteps=6_000_000, lr_schedule="cyclic", cycle_steps=1_000_000,
                                           num_steps=2048),
                                      dict(total_timesteps=5_000_000, lr_schedule="cyclic", cycle_steps=1_500_000,
                                           num_steps=2048),
                                      dict(total_timesteps=6_000_000, lr_schedule="global", num_steps=2048),
                                      dict(total_timesteps=6_000_000, num_steps=1000)])
def test_export_plans_the_steps_the_baseline_runs(settings):
    """export_results.py counted a cyclic baseline's budget as one total (2929 rollouts for 6M steps in cycles of 1M)
    after the script had moved to whole cycles (2928): the re-run of Fig. 3's baseline was skipped as unfinished.
    The plan must be the script's own count, from what the run logs."""
    from cascade_plumbing.ppo import baseline_updates
    from plots.export_results import planned_steps

    args = ppo_baseline.Args(env_id="Hopper-v4", **settings)
    batch = args.num_envs * args.num_steps
    logged = {key: str(value) for key, value in dataclasses.asdict(args).items()}
    assert planned_steps(logged) == baseline_updates(args, batch) * batch


def test_an_exported_run_under_another_name_or_with_damaged_series_is_one_line(tmp_path):
    """A results-pipeline hunt: an exported Walker2d run copied under Hopper's name was averaged into Hopper's curve,
    one seed copied under another seed's name counted twice, and a values list shorter than its steps was cut
    silently; a run folder refused the first two already."""
    import json

    source = os.path.join(ROOT, "results", "per_run", "Walker2d-v4__ppo_h16_cyclic__1__1796696625.json")
    common.read_run(source)  # as committed: read
    data = json.load(open(source))
    cases = [("Hopper-v4__ppo_h16_cyclic__1__1796696625.json", data, "holds the run Walker2d-v4__ppo_h16_cyclic__1"),
             ("Walker2d-v4__ppo_h16_cyclic__2__1796696625.json", data, "holds the run Walker2d-v4__ppo_h16_cyclic__1"),
             ("Hopper-v4__ppo_h16_cyclic__1__1.json", {**data, "name": "Hopper-v4__ppo_h16_cyclic__1__1"},
              "is named for env_id=Hopper-v4 but the run logged env_id=Walker2d-v4")]
    short = json.loads(json.dumps(data))
    short["scalars"]["eval/episodic_return"]["values"].pop()
    cases.append((os.path.basename(source), short, "cannot read exported run"))
    empty = json.loads(json.dumps(data))  # (reproduce.py ended in a traceback from the final scores)
    empty["scalars"]["eval/episodic_return"] = {"steps": [], "values": [], "wall_times": []}
    cases.append((os.path.basename(source), empty, "eval/episodic_return is empty"))
    for name, content, message in cases:
        path = tmp_path / name
        path.write_text(json.dumps(content))
        with pytest.raises(SystemExit) as stop:
            common.read_run(str(path))
        assert message in str(stop.value) and "\n" not in str(stop.value), stop.value


def test_a_sweeps_completion_markers_are_not_read_as_exported_runs(tmp_path):
    """sweep.py's done/<env>__<exp>__<seed>__<hash>.json looks like an exported run when the 10-hex hash is all
    digits (~1 run in 100): `--runs sweeps/x` stopped with "cannot read exported run ... re-export it"."""
    sweep_dir = tmp_path / "sweep"
    (sweep_dir / "done").mkdir(parents=True)
    (sweep_dir / "runs").mkdir()
    (sweep_dir / "done" / "Hopper-v4__cascade__1__1234567890.json").write_text('{"run_id": "x"}')
    exported = tmp_path / "per_run"
    exported.mkdir()
    shutil.copy(os.path.join(ROOT, "results", "per_run", "Walker2d-v4__ppo_h16_cyclic__1__1796696625.json"), exported)
    assert common.find_run_dirs([str(sweep_dir)]) == []
    # a folder named done elsewhere is searched as any other
    (exported / "done").mkdir()
    shutil.move(str(exported / "Walker2d-v4__ppo_h16_cyclic__1__1796696625.json"), str(exported / "done"))
    assert len(common.find_run_dirs([str(exported)])) == 1
