"""Bad settings shared by every training script are refused in one line, before anything is written
(issue 18: these gave tracebacks, left run folders, or were silently accepted)."""

import importlib
import os
import signal
import time
from types import SimpleNamespace

import gymnasium as gym
import pytest

from helpers import error_line, error_line_in_process, run_in_process, run_script

SCRIPTS = ["cascade_ppo_continuous", "ppo_baseline", "cascade_ppo_discrete", "ppo_baseline_discrete", "cascade_sac",
           "cascade_ddpg"]
PPO = SCRIPTS[:4]
ENV = {"cascade_ppo_discrete": "CartPole-v1", "ppo_baseline_discrete": "CartPole-v1"}


def cases(script):
    rates = {"cascade_sac": [("policy_lr", "--policy-lr"), ("q_lr", "--q-lr")]}.get(script, [("learning_rate",
                                                                                                "--learning-rate")])
    out = [(dict(seed=-1), "--seed must be a non-negative integer"),
           (dict(torch_threads=0), "--torch-threads must be at least 1"),
           # with evaluation off too (a fresh-user hunt: -1 episodes was accepted, and the run trained)
           (dict(eval_episodes=-1, eval_every=0), "--eval-episodes >= 1")]
    if script not in ("cascade_sac", "cascade_ddpg"):  # they checkpoint at iteration ends only
        out.append((dict(checkpoint_every=-1), "--checkpoint-every must be >= 0"))
    out += [({field: -1.0}, f"{flag} must be >= 0") for field, flag in rates]
    if script in PPO:
        out += [(dict(num_minibatches=0), "--num-minibatches and --update-epochs must be at least 1"),
                (dict(update_epochs=0), "--num-minibatches and --update-epochs must be at least 1")]
    if script in ("ppo_baseline", "ppo_baseline_discrete"):  # a cycle length without cycles was silently ignored
        out.append((dict(cycle_steps=500_000), "--cycle-steps has no effect with --lr-schedule global"))
    return out


@pytest.mark.parametrize("script,overrides,message",
                         [(s, o, m) for s in SCRIPTS for o, m in cases(s)],
                         ids=[f"{s}-{next(iter(o))}" for s in SCRIPTS for o, _ in cases(s)])
def test_bad_setting_is_one_line_and_leaves_nothing(script, overrides, message, tmp_path):
    module = importlib.import_module(script)
    args = module.Args(env_id=ENV.get(script, "Hopper-v4"), track_dir=str(tmp_path / "runs"), **overrides)
    with pytest.raises(SystemExit) as stop:
        module.train(args)
    text = str(stop.value)
    assert text.startswith("error:") and message in text and "\n" not in text, text
    assert not (tmp_path / "runs").exists()
    assert list(tmp_path.iterdir()) == []  # the writability probe leaves nothing behind


@pytest.mark.parametrize("script", SCRIPTS)
def test_track_dir_must_be_a_writable_folder(script, tmp_path):
    module = importlib.import_module(script)
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    for track_dir, message in [(a_file, "is a file, not a folder"), (a_file / "runs", "cannot create run folders")]:
        args = module.Args(env_id=ENV.get(script, "Hopper-v4"), track_dir=str(track_dir))
        with pytest.raises(SystemExit) as stop:
            module.train(args)
        assert message in str(stop.value) and "\n" not in str(stop.value), str(stop.value)


@pytest.mark.parametrize("script", SCRIPTS)
def test_evaluate_with_no_episodes_is_refused(script, tmp_path):
    module = importlib.import_module(script)
    with pytest.raises(SystemExit) as stop:
        module.evaluate_saved(module.Args(evaluate=str(tmp_path / "nope"), eval_episodes=0))
    assert "--eval-episodes must be at least 1" in str(stop.value)


def test_num_envs_that_break_the_batch_say_which_work(tmp_path):
    line = error_line(run_script("cascade_ppo_continuous.py", "--num-envs", "3", "--track-dir", tmp_path / "runs"))
    assert "2046" in line and "--num-envs 1, 2, 4, 8, 16 work" in line
    assert not (tmp_path / "runs").exists()


def range_cases(script):
    """Issue 49.5: values each script took and trained with until the non-finite guard stopped the run (inf, NaN),
    or accepted silently (a negative exploration noise)."""
    nan, inf = float("nan"), float("inf")
    rate = {"cascade_sac": "policy_lr"}.get(script, "learning_rate")
    out = [({rate: inf}, f"--{rate.replace('_', '-')} must be a finite number (got inf)"),
           (dict(gamma=nan), "--gamma must be a finite number (got nan)"),
           (dict(gamma=1.5), "--gamma must lie in [0, 1] (got 1.5)")]
    if script in PPO:
        out += [(dict(clip_coef=nan), "--clip-coef must be a finite number (got nan)"),
                (dict(clip_coef=0.0), "--clip-coef must be > 0 (got 0.0)"),
                (dict(gae_lambda=-0.1), "--gae-lambda must lie in [0, 1] (got -0.1)"),
                (dict(target_kl=-inf), "--target-kl must be a finite number (got -inf)")]
    if script == "cascade_sac":
        out += [(dict(alpha=nan), "--alpha must be a finite number (got nan)"),
                (dict(alpha=-0.2), "--alpha must be >= 0 (got -0.2)"),
                (dict(q_lr=inf), "--q-lr must be a finite number (got inf)"),
                (dict(tau=0.0), "--tau must lie in (0, 1] (got 0.0)")]
    if script == "cascade_ddpg":
        out += [(dict(exploration_noise=nan), "--exploration-noise must be a finite number (got nan)"),
                (dict(exploration_noise=-0.1), "--exploration-noise must be >= 0 (got -0.1)")]
    return out


@pytest.mark.parametrize("script,overrides,message",
                         [(s, o, m) for s in SCRIPTS for o, m in range_cases(s)],
                         ids=[f"{s}-{next(iter(o))}-{next(iter(o.values()))}" for s in SCRIPTS for o, _ in range_cases(s)])
def test_a_setting_outside_its_range_is_one_line_and_leaves_nothing(script, overrides, message, tmp_path):
    test_bad_setting_is_one_line_and_leaves_nothing(script, overrides, message, tmp_path)


@pytest.mark.parametrize("script", SCRIPTS)
def test_a_non_finite_learning_rate_on_the_command_line_is_one_line(script, tmp_path):
    """As a user meets it: `--learning-rate inf` (SAC: `--policy-lr`), one line, exit 1, no run folder."""
    flag = "--policy-lr" if script == "cascade_sac" else "--learning-rate"
    line = error_line_in_process(f"{script}.py", "--env-id", ENV.get(script, "Hopper-v4"), flag, "inf",
                                 "--track-dir", str(tmp_path / "runs"))
    assert line == f"error: {flag} must be a finite number (got inf)"
    assert not (tmp_path / "runs").exists()


def missing_dependency(**kwargs):
    raise gym.error.DependencyNotInstalled('Box2D is not installed, run `pip install "gymnasium[box2d]"`')


@pytest.mark.parametrize("script", SCRIPTS)
def test_a_registered_env_whose_package_is_missing_is_one_line(script, tmp_path):
    """A registered env that cannot be made here (LunarLander-v3 without Box2D, a shimmy env without shimmy) was a
    ~45-line traceback from the env probe; now one line with gymnasium's own advice."""
    if "MissingPackage-v0" not in gym.envs.registry:
        gym.register(id="MissingPackage-v0", entry_point=missing_dependency)
    module = importlib.import_module(script)
    with pytest.raises(SystemExit) as stop:
        module.train(module.Args(env_id="MissingPackage-v0", track_dir=str(tmp_path / "runs")))
    text = str(stop.value)
    assert text == ('error: cannot make MissingPackage-v0: Box2D is not installed, run `pip install "gymnasium[box2d]"`; '
                    "install what it needs, or pick another --env-id"), text
    assert not (tmp_path / "runs").exists()


class ShapedObservationEnv(gym.Env):
    """An env whose observations no script's MLP takes: an image, or a Dict (goal envs)."""

    def __init__(self, observation_space, action_space):
        self.observation_space, self.action_space = observation_space, action_space

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return self.observation_space.sample(), {}

    def step(self, action):
        return self.observation_space.sample(), 0.0, False, False, {}


BOX_ACTIONS, TWO_ACTIONS = gym.spaces.Box(-1.0, 1.0, (2,)), gym.spaces.Discrete(2)
IMAGE, VECTOR = gym.spaces.Box(0.0, 1.0, (8, 8, 3)), gym.spaces.Box(-1.0, 1.0, (3,))
SHAPED_ENVS = {"CascadeTestImage-v0": (IMAGE, BOX_ACTIONS), "CascadeTestImageDiscrete-v0": (IMAGE, TWO_ACTIONS),
               "CascadeTestDict-v0": (gym.spaces.Dict({"observation": VECTOR, "goal": VECTOR}), BOX_ACTIONS)}
for env_id, spaces in SHAPED_ENVS.items():
    gym.register(id=env_id, entry_point=ShapedObservationEnv, kwargs=dict(zip(("observation_space", "action_space"),
                                                                             spaces)), max_episode_steps=5)


@pytest.mark.parametrize("env_id,what", [("CascadeTestImage-v0", "observations of shape (8, 8, 3)"),
                                         ("CascadeTestImageDiscrete-v0", "observations of shape (8, 8, 3)"),
                                         ("CascadeTestDict-v0", "a Dict observation space"),
                                         ("FrozenLake-v1", "a Discrete observation space")])
@pytest.mark.parametrize("script", SCRIPTS)
def test_observations_that_are_not_a_flat_box_are_one_line(script, env_id, what, tmp_path):
    """An image or Dict observation was a traceback deep in the PPO scripts' first rollout (a fresh-user hunt,
    2026-12-08), and FrozenLake-v1 sent the continuous scripts' user to the discrete ones, which then refused it: the
    observations are checked first, alike in every script."""
    module = importlib.import_module(script)
    with pytest.raises(SystemExit) as stop:
        module.train(module.Args(env_id=env_id, track_dir=str(tmp_path / "runs")))
    text = str(stop.value)
    assert text.startswith(f"error: {env_id} has {what};") and "flat (1-D) Box" in text and "\n" not in text, text
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize("script,twin", [("cascade_ppo_continuous", "cascade_ppo_discrete.py"),
                                         ("ppo_baseline", "ppo_baseline_discrete.py")])
def test_a_discrete_env_names_the_discrete_twin_of_the_script(script, twin, tmp_path):
    """ppo_baseline.py sent a user with CartPole-v1 to cascade_ppo_discrete.py, not to its own discrete twin."""
    module = importlib.import_module(script)
    with pytest.raises(SystemExit) as stop:
        module.train(module.Args(env_id="CartPole-v1", track_dir=str(tmp_path / "runs")))
    assert str(stop.value).endswith(f"this script needs a Box (continuous) one: use {twin}"), stop.value


@pytest.mark.parametrize("script", SCRIPTS)
def test_a_seed_numpy_refuses_is_one_line(script, tmp_path):
    """Seeds of 2**32 and more (a hash, `date +%s%N`) were a traceback from np.random.seed."""
    module = importlib.import_module(script)
    args = module.Args(env_id=ENV.get(script, "Hopper-v4"), track_dir=str(tmp_path / "runs"), seed=2**32)
    with pytest.raises(SystemExit) as stop:
        module.train(args)
    assert str(stop.value).startswith(f"error: --seed must be a non-negative integer below 2**32 (got {2**32})")
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize("script", SCRIPTS)
def test_evaluate_refuses_flags_it_would_ignore_in_one_line(script, tmp_path):
    """--evaluate runs the saved model on its own env: a --env-id or --resume beside it was silently dropped (a
    Pendulum model "evaluated" on Hopper-v4 printed Pendulum's returns), a seed numpy refuses was a traceback."""
    saved = str(tmp_path / "run")
    cases = [(["--env-id", "Hopper-v4"], "--env-id has no effect with --evaluate"),
             (["--resume", saved], "--evaluate and --resume exclude each other"),
             (["--seed", str(2**32)], "--seed must be a non-negative integer below 2**32"),
             # any training setting was silently ignored too (the audit of issue 48)
             (["--gamma", "0.9"], "--gamma has no effect with --evaluate"),
             (["--eval-episodes", "2", "--track-dir", "elsewhere"], "--track-dir has no effect with --evaluate")]
    for flags, message in cases:
        line = error_line_in_process(f"{script}.py", "--evaluate", saved, *flags)
        assert line.startswith(f"error: {message}"), line
    # the flags that apply are named; --quiet and --cuda, let be for job scripts, are not among them (a fresh-user hunt)
    line = error_line_in_process(f"{script}.py", "--evaluate", saved, "--gamma", "0.9")
    assert "--eval-episodes" in line.partition("apply")[0] and "--quiet" not in line and "--cuda" not in line, line


def test_torch_threads_below_one_is_one_line_wherever_it_is_set():
    """--evaluate sets torch's threads without the training checks: --torch-threads 0 was torch's traceback."""
    from cascade_plumbing.runs import set_threads

    with pytest.raises(SystemExit) as stop:
        set_threads(0)
    assert str(stop.value) == "error: --torch-threads must be at least 1 (got 0)"


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_stopped_evaluation_is_one_line(signum, capsys):
    """Ctrl-C or SIGTERM during --evaluate was a KeyboardInterrupt traceback (or a silent death by SIGTERM): now one
    line and exit 130 / 143, as for a stopped run."""
    from cascade_plumbing import runs

    def evaluation_stopped(args):
        os.kill(os.getpid(), signum)
        time.sleep(10)  # the handler interrupts this
        raise AssertionError("the stop did not reach the evaluation")

    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    args = SimpleNamespace(evaluate="runs/some_run", resume=None, seed=1)
    try:
        # Ctrl-C in a terminal: Python's own handler (a test run started in the background, `cmd &`, inherits an
        # ignored SIGINT, which the script rightly leaves ignored)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        with pytest.raises(SystemExit) as stop:
            runs.evaluate_only(args, set(), evaluation_stopped, lambda path, reader_flag="": {"path": path})
    finally:
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
    assert stop.value.code == 128 + signum
    line = capsys.readouterr().err.strip("\r\n")
    assert line == (f"stopped by {signal.Signals(signum).name}: the evaluation of runs/some_run was stopped before it "
                    "ended (nothing to resume: run it again)"), line


@pytest.mark.parametrize("script", SCRIPTS)
def test_run_names_and_empty_paths_are_refused(script, tmp_path, monkeypatch):
    """Audit: an empty --resume / --evaluate (`--resume "$RUN"` with RUN unset) started a new full-length run; an
    --exp-name with a '/' or an empty --track-dir was a FileNotFoundError traceback (and left a folder)."""
    module = importlib.import_module(script)
    monkeypatch.chdir(tmp_path)
    for overrides, message in [(dict(exp_name="a/b"), "--exp-name 'a/b': it names the run folder"),
                               (dict(exp_name=" "), "--exp-name ' ': it names the run folder"),
                               (dict(track_dir=""), "--track-dir is empty")]:
        args = module.Args(env_id=ENV.get(script, "Hopper-v4"), **{"track_dir": str(tmp_path / "runs"), **overrides})
        with pytest.raises(SystemExit) as stop:
            module.train(args)
        assert str(stop.value).startswith(f"error: {message}") and "\n" not in str(stop.value), str(stop.value)
    for flag in ("--resume", "--evaluate"):
        assert error_line_in_process(f"{script}.py", flag, "", "--track-dir", str(tmp_path / "runs")) == \
            f"error: {flag} is empty; pass a run folder or a checkpoint file"
    assert list(tmp_path.iterdir()) == []


def test_nets_too_large_for_the_machine_are_one_line_and_leave_no_folder(tmp_path):
    """Audit: --hidden-size 1000000 was torch's allocator traceback and left a run folder holding only an event
    file (every script: the handler is run_main's). 10^7 units: a 10^7 x 10^7 layer is 400 TB, beyond any machine's
    address space, so the allocation fails everywhere, overcommit or not."""
    line = error_line_in_process("cascade_ppo_continuous.py", "--env-id", "Hopper-v4", "--hidden-size", "10000000",
                                 "--track-dir", str(tmp_path / "runs"))
    assert line.startswith("error: out of memory before the run's first checkpoint (can't allocate memory"), line
    assert line.endswith("start again with smaller nets or batches (--hidden-size, --num-envs, --num-steps) or a "
                         "machine with more"), line  # (the flags this script has)
    assert not (tmp_path / "runs").exists() or os.listdir(tmp_path / "runs") == []


IDLE_FLAGS = [  # (script, flags, the line): flags a training run cannot act on, accepted silently before (audit)
    ("cascade_ppo_continuous", ["--members"], "--members applies to --evaluate only (training's evaluation of each "
                                              "net: --eval-members)"),
    ("cascade_ppo_discrete", ["--deterministic"], "--deterministic applies to --evaluate only"),
    ("ppo_baseline", ["--wandb-group", "g"], "--wandb-group applies with --track only"),
    ("cascade_ddpg", ["--n", "1", "--keep-buffer"], "--keep-buffer has no effect with --n 1"),
    ("cascade_sac", ["--n", "1", "--reset-critic"], "--reset-critic has no effect with --n 1"),
    # (a new-user pass: each ran with exit 0)
    ("cascade_sac", ["--n", "1", "--fallback-init", "0.9"], "--fallback-init has no effect with --n 1"),
    ("cascade_ppo_discrete", ["--n", "1", "--freeze-previous"], "--freeze-previous has no effect with --n 1"),
    ("cascade_ddpg", ["--eval-every", "0", "--eval-members"], "--eval-members has no effect with --eval-every 0"),
    ("cascade_sac", ["--eval-every", "0", "--eval-deterministic"], "--eval-deterministic has no effect with --eval-"),
    # (a fault hunt: accepted silently, the PPO scripts evaluate the nets alone with the periodic evaluation only)
    ("cascade_ppo_continuous", ["--eval-every", "0", "--eval-members"], "--eval-members has no effect with --eval-"),
    ("ppo_baseline", ["--eval-every", "0", "--eval-in-worker"], "--eval-in-worker has no effect with --eval-every 0"),
    # (a fresh-user hunt, 2026-12-08: each ran with exit 0, the same run as without them)
    ("cascade_ppo_continuous", ["--n", "1", "--start-full"], "--start-full has no effect with --n 1"),
    ("cascade_ppo_discrete", ["--n", "1", "--lr-schedule", "global"], "--lr-schedule global is the standard cyclic "
                                                                       "schedule with --n 1"),
]


@pytest.mark.parametrize("script,flags,message", IDLE_FLAGS, ids=[f"{s}-{f[-1]}" for s, f, _ in IDLE_FLAGS])
def test_flags_a_training_run_cannot_act_on_are_refused(script, flags, message, tmp_path):
    # tiny budgets: where the check is broken the run trains, ends in seconds and the test fails (not hangs)
    budget = {"cascade_ppo_continuous": ["--k", "2048"], "ppo_baseline": ["--total-timesteps", "2048"],
              "cascade_ppo_discrete": ["--k", "512"], "cascade_sac": ["--k", "300", "--learning-starts", "100"],
              "cascade_ddpg": ["--k", "300", "--learning-starts", "100"]}[script]
    line = error_line_in_process(f"{script}.py", "--env-id", ENV.get(script, "Hopper-v4"), *budget, *flags,
                                 "--track-dir", str(tmp_path / "runs"))
    assert line.startswith(f"error: {message}") and line.endswith("; leave it out"), line
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize("script", ["cascade_ppo_discrete", "ppo_baseline_discrete"])
def test_normalize_on_a_natively_discrete_env_is_refused(script, tmp_path):
    """Known gap: --normalize on CartPole was accepted and ignored (natively discrete envs are never normalized)."""
    budget = ["--k", "512"] if script == "cascade_ppo_discrete" else ["--total-timesteps", "512"]  # (if it ran)
    line = error_line_in_process(f"{script}.py", "--env-id", "CartPole-v1", "--normalize", *budget,
                                 "--track-dir", str(tmp_path / "runs"))
    assert line == ("error: --normalize applies to discretized Box envs only: CartPole-v1 is natively discrete and "
                    "is never normalized or clipped (as CleanRL ppo.py); leave it out"), line
    assert not (tmp_path / "runs").exists() or os.listdir(tmp_path / "runs") == []


@pytest.mark.parametrize("script", ["cascade_ppo_discrete", "ppo_baseline_discrete"])
@pytest.mark.parametrize("rate,line", [("1e30", "error: non-finite loss or parameters at global_step=512"),
                                       ("1e300", "error: a value overflowed float32 (value cannot be converted")])
def test_a_diverging_discrete_run_stops_in_one_line(script, rate, line, tmp_path):
    """A fault hunt: a NaN in one minibatch made the next minibatch's Categorical raise its argument check (a
    traceback with a tensor dump) before the non-finite guard ran; a learning rate beyond float32 was Adam's
    overflow traceback (every script: run_main's handler)."""
    budget = ["--n", "1", "--k", "1024"] if script == "cascade_ppo_discrete" else ["--total-timesteps", "1024"]
    got = error_line_in_process(f"{script}.py", "--env-id", "CartPole-v1", *budget, "--learning-rate", rate,
                                "--eval-every", "0", "--track-dir", str(tmp_path / "runs"))
    assert got.startswith(line) and got.endswith("start a new run with a lower --learning-rate (or another --seed)"), got


@pytest.mark.parametrize("script,flags", [
    ("cascade_ppo_continuous", ["--env-id", "Pendulum-v1", "--n", "1", "--k", "8"]),
    ("ppo_baseline", ["--env-id", "Pendulum-v1", "--total-timesteps", "8"]),
    ("cascade_ppo_discrete", ["--env-id", "CartPole-v1", "--n", "1", "--k", "8"]),
    ("ppo_baseline_discrete", ["--env-id", "CartPole-v1", "--total-timesteps", "8"])])
def test_a_minibatch_of_one_row_with_advantage_normalization_is_refused(script, flags, tmp_path):
    """A fault hunt: accepted, then the std of one advantage was NaN: a misleading fast-path warning and 'lower
    --learning-rate' (continuous), a traceback (discrete). With --no-norm-adv such a run is fine."""
    common = ["--num-envs", "1", "--num-steps", "4", "--num-minibatches", "4", "--eval-every", "0"]
    line = error_line_in_process(f"{script}.py", *flags, *common, "--track-dir", str(tmp_path / "runs"))
    assert line == ("error: a minibatch of one row (batch 4 in --num-minibatches 4) cannot normalize its advantages "
                    "(--norm-adv); lower --num-minibatches, raise --num-steps or --num-envs, or pass --no-norm-adv")
    assert not (tmp_path / "runs").exists() or os.listdir(tmp_path / "runs") == []
    assert run_in_process(f"{script}.py", *flags, *common, "--no-norm-adv", "--quiet",
                          "--track-dir", str(tmp_path / "ok"))[0] == 0


def test_an_unknown_env_id_suggests_ids_that_can_be_made_here():
    """Audit: `--env-id Hopper` suggested Hopper-v3, which needs the retired mujoco-py and cannot be made here;
    now the versions of that name that can be made, the one asked for first."""
    from cascade_plumbing.envs import check_env_id

    for asked, suggested in [("Hopper", "Hopper-v5, Hopper-v4"), ("hopper-v4", "Hopper-v4, Hopper-v5")]:
        with pytest.raises(SystemExit) as stop:
            check_env_id(asked)
        assert f"unknown env id '{asked}'. Did you mean {suggested}" in str(stop.value), str(stop.value)
        assert "Hopper-v3" not in str(stop.value) and "Hopper-v2" not in str(stop.value)
    assert "Hopper-v3" in gym.envs.registry  # registered all the same: the suggestion filters it out
    # and asked for itself, the line that it cannot be made names those that can (a fresh-user hunt, 2026-12-08)
    from cascade_plumbing.envs import probe_spaces

    with pytest.raises(SystemExit) as stop:
        probe_spaces("Hopper-v3")
    assert str(stop.value).startswith("error: cannot make Hopper-v3: ") and \
        str(stop.value).endswith("pick another --env-id (Hopper-v5, Hopper-v4 can be made here)"), str(stop.value)


def test_a_flag_given_at_its_default_value_is_checked_too(tmp_path):
    """A fault hunt: `--autotune --alpha 0.2` and `--cycle-steps 1000000` with the global schedule were accepted
    (the check compared the value with the default), while `--alpha 0.3` and `--cycle-steps 500000` were refused."""
    for script, flags, message in [
            ("cascade_sac", ["--env-id", "Pendulum-v1", "--n", "1", "--k", "300", "--learning-starts", "100",
                             "--autotune", "--alpha", "0.2"], "error: --alpha 0.2 has no effect with --autotune"),
            ("ppo_baseline", ["--env-id", "Pendulum-v1", "--total-timesteps", "2048", "--cycle-steps", "1000000"],
             "error: --cycle-steps has no effect with --lr-schedule global"),
            ("ppo_baseline_discrete", ["--env-id", "CartPole-v1", "--total-timesteps", "512", "--cycle-steps",
                                       "1000000"], "error: --cycle-steps has no effect with --lr-schedule global")]:
        line = error_line_in_process(f"{script}.py", *flags, "--eval-every", "0", "--track-dir", str(tmp_path))
        assert line.startswith(message), line


def test_a_switch_turned_off_is_never_an_idle_flag(tmp_path):
    """A fault hunt: `--no-keep-buffer` with --n 1 was refused as '--keep-buffer has no effect' (a job script or a
    sweep template that spells out the defaults). A switch turned off asks for nothing the run would not do."""
    for script, flags in [("cascade_sac", ["--env-id", "Pendulum-v1", "--n", "1", "--k", "300", "--learning-starts",
                                           "100", "--no-keep-buffer", "--no-eval-members", "--eval-every", "0"]),
                          ("cascade_ppo_continuous", ["--env-id", "Pendulum-v1", "--n", "1", "--k", "2048",
                                                      "--no-deterministic", "--no-members", "--eval-every", "0"])]:
        code, message = run_in_process(f"{script}.py", *flags, "--quiet", "--track-dir", str(tmp_path / script))
        assert code == 0, message


def test_a_run_started_with_an_idle_flag_still_resumes(tmp_path, capsys):
    """Review: the idle-flag check ran on --resume too, so a run started before it (or a sweep's resume, which repeats
    the template's flags) with e.g. --n 1 --keep-buffer could no longer be continued. Only new runs are checked."""
    import cascade_ddpg
    from helpers import cli_in_process

    flags = dict(env_id="Pendulum-v1", n=1, k=300, learning_starts=100, batch_size=32, eval_every=0, quiet=True)
    run_dir = cascade_ddpg.train(cascade_ddpg.Args(keep_buffer=True, track_dir=str(tmp_path), **flags))["run_dir"]
    code, out, message = cli_in_process(capsys, "cascade_ddpg.py", "--resume", run_dir, "--n", "1", "--keep-buffer")
    assert code == 0 and "is the end of the run" in out, (out, message)


@pytest.mark.parametrize("script", ["cascade_ppo_continuous", "cascade_sac"])
def test_a_hand_made_file_with_our_format_is_one_line(script, tmp_path):
    """Audit: a file holding only our format key (made by hand, or a truncated save of another tool) gave KeyError
    tracebacks with --evaluate and --resume."""
    import torch

    module = importlib.import_module(script)
    path = tmp_path / "made_by_hand.pt"
    torch.save({"format": module.CHECKPOINT_FORMAT}, path)
    for flag in ("--evaluate", "--resume"):
        line = error_line_in_process(f"{script}.py", flag, str(path))
        assert line == (f"error: {path} is an incomplete {script} checkpoint (no args, global_step): not one that "
                        f"{script}.py wrote; pass a run folder or a checkpoint file it wrote"), line


@pytest.mark.parametrize("script,flags,message", [
    ("cascade_sac.py", ["--nn", "3"], "error: Unrecognized options: --nn, 3 (did you mean --n?); see "),
    ("cascade_ppo_continuous.py", ["--learning-rate", "x"],
     "error: Error parsing --learning-rate: could not convert string to float: 'x'; see "),
    ("ppo_baseline_discrete.py", ["--env-id"], "error: Missing value for argument '--env-id'. Expected 1 values; see"),
    ("cascade_ddpg.py", ["--hidden_siz", "4"], "(did you mean --hidden-size?)"),
    ("sweep.py", ["--presett", "sac"], "error: Unrecognized options: --presett, sac (did you mean --preset?)"),
    ("plots/learning_curves.py", ["--nope"], "error: Unrecognized options: --nope; see "),
    ("plots/analyze.py", ["fallback-course"], "analyze.py fallback-course: --checkpoint; see "),
    # a flag of a subcommand given before it: the flag, tyro's note and the subcommand the suggestions belong to
    ("plots/analyze.py", ["table2", "--observations-from", "after"], "error: Unrecognized or misplaced options: "
     "--observations-from, after (did you mean --observations-from of "),
])
def test_a_flag_the_command_line_cannot_parse_is_one_line(script, flags, message):
    """tyro's parse errors (an unknown or misspelt flag, a value of the wrong type, a missing value or option) were
    a box of up to a dozen lines with the flag's whole help; now one line: what is wrong, the flag tyro suggests,
    and the --help to read (exit 2, as tyro's)."""
    proc = run_script(script, *flags, timeout=120)
    line = error_line(proc)
    assert proc.returncode == 2 and message in line and line.endswith(f"{script} --help"), line


@pytest.mark.parametrize("box,expected", [
    # as a narrow terminal wraps it: the sentence joined again; the flag's help left out
    ("\u256d\u2500 Value error \u2500\u2500\u256e\n\u2502 Error parsing --k: invalid literal for \u2502\n"
     "\u2502 int() with base 10: 'abc' \u2502\n\u2502 \u2500\u2500\u2500\u2500\u2500\u2500 \u2502\n"
     "\u2502 Argument helptext: \u2502\n\u2502     --k INT \u2502\n\u2502     steps per net \u2502\n"
     "\u2502 \u2500\u2500\u2500\u2500\u2500\u2500 \u2502\n\u2502 For full helptext, see x.py --help \u2502\n"
     "\u2570\u2500\u2500\u2500\u2500\u256f\n", "Error parsing --k: invalid literal for int() with base 10: 'abc'"),
    # plain text with dashed rules; two suggestions, each with help lines that start with a flag
    ("Unrecognized options\n------\nUnrecognized options: --lr\n------\nPerhaps you meant:\n    --q-lr FLOAT\n"
     "        --q-lr is the critics' rate\n    --policy-lr FLOAT\n        the actor's\n------\n"
     "For full helptext, run x.py --help\n", "Unrecognized options: --lr (did you mean --q-lr or --policy-lr?)"),
    # coloured, as tyro writes it to a terminal; a boolean flag's two spellings
    ("\x1b[31m\u256d\u2500 Unrecognized options \u2500\u256e\x1b[0m\n\u2502 \x1b[1mUnrecognized options: --eval-det"
     "\x1b[0m \u2502\n\u2502 \u2500\u2500\u2500\u2500 \u2502\n\u2502 Perhaps you meant: \u2502\n"
     "\u2502     --eval-deterministic, --no-eval-deterministic \u2502\n\u2502         greedy actions \u2502\n"
     "\u2502 \u2500\u2500\u2500\u2500 \u2502\n\u2502 For full helptext, run x.py --help \u2502\n"
     "\u2570\u2500\u2500\u2500\u256f\n", "Unrecognized options: --eval-det (did you mean --eval-deterministic?)"),
    # the plain form as tyro writes it when stdout is not a terminal (sweep.py's check of a template): a 2-space margin
    (" Unrecognized options          \n ------------------------------ \n  Unrecognized options: --bogus, 3\n"
     "  ------------------------------\n  Perhaps you meant:\n      --n INT\n          number of nets\n"
     "  ------------------------------\n  For full helptext, run sweep.py --help  \n                   \n",
     "Unrecognized options: --bogus, 3 (did you mean --n?)"),
    ("a run's last line\n", None),
])
def test_parse_error_line_reads_tyros_box_and_plain_forms(box, expected):
    from cascade_plumbing.errors import parse_error_line

    assert parse_error_line(box) == expected


def test_a_parse_error_on_a_terminal_is_one_line_too():
    """On a terminal tyro colours its box (ANSI codes), which the one-line reading did not see through: the box
    came out as before. Run under a pseudo-terminal, as a user types the command."""
    import pty
    import subprocess
    import sys

    from helpers import ROOT

    leader, follower = pty.openpty()
    proc = subprocess.run([sys.executable, os.path.join(ROOT, "cascade_sac.py"), "--nn", "3"], stdin=follower,
                          stdout=follower, stderr=follower, cwd=ROOT, timeout=120, env={**os.environ, "TERM": "xterm"})
    os.close(follower)
    said = b""
    while True:
        try:
            chunk = os.read(leader, 4096)
        except OSError:  # the terminal's other end is closed: all was read
            break
        if not chunk:
            break
        said += chunk
    os.close(leader)
    lines = [line for line in said.decode().splitlines() if line.strip()]
    assert proc.returncode == 2 and lines == [
        "error: Unrecognized options: --nn, 3 (did you mean --n?); see " f"{os.path.join(ROOT, 'cascade_sac.py')} --help"], said


def test_what_tyro_prints_before_its_error_is_kept(capsys):
    """A warning tyro prints while parsing stays on stderr, before the one line that replaces its error box."""
    import sys

    from cascade_plumbing.errors import parse_command_line

    def parse():
        print("UserWarning: a field without a docstring", file=sys.stderr)
        print("Unrecognized options\n------\nUnrecognized options: --lr\n------\nFor full helptext, run x.py --help",
              file=sys.stderr)
        raise SystemExit(2)

    with pytest.raises(SystemExit) as stop:
        parse_command_line(parse)
    assert stop.value.code == 2
    assert capsys.readouterr().err.splitlines() == [
        "UserWarning: a field without a docstring", f"error: Unrecognized options: --lr; see {sys.argv[0]} --help"]


def test_a_parse_error_is_read_whole_on_a_narrow_terminal():
    """tyro draws its box to the terminal's width: on a narrow one a flag's line wrapped, and its wrapped part read as
    another flag (`--eval-deterministic or --no-eval-deterministic`), or a heading that wrapped (a long path in
    "Missing from <path> fallback-course:") as a sentence with the flag's whole help."""
    narrow = {"COLUMNS": "40"}
    line = error_line(run_script("cascade_sac.py", "--eval-deterministicc", env=narrow))
    assert "(did you mean --eval-deterministic?)" in line, line
    line = error_line(run_script("plots/analyze.py", "fallback-course", env=narrow))
    assert "analyze.py fallback-course: --checkpoint; see " in line, line
