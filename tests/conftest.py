import os
import sys

import pytest
import torch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
torch.set_num_threads(1)


# The longest tests (>= ~30 s each on 2 busy cores; `--durations=60`, 2026-12-03), longest first. They are handed
# out first, and pytest-xdist hands out one test at a time (--maxschedchunk 1, below), so that no long test
# starts last and leaves one worker alone at the end. Only tests without module-scoped fixtures (moving one away
# from its module would build the fixture twice), but for test_plots' first test: its fixture is built once for
# all workers (helpers.built_once), early, so that no worker waits for it later. A stale entry costs time, never
# correctness.
LONG_FIRST = (
    "test_sac_ddpg.py::test_learns",
    "test_discrete.py::test_cascade_learns_cartpole",
    "test_sac_ddpg.py::test_hopper_smoke_run_scalars_checkpoints_resume_and_evaluate",
    "test_checkpoints.py::test_baseline_checkpoint_resume_and_evaluate",
    "test_training.py::test_learns_inverted_pendulum",
    "test_tracking.py::test_sac_tracked_with_videos",
    "test_sweep.py::test_rerun_with_other_budget_starts_a_new_run",
    "test_sweep.py::test_ray_sweep_on_a_real_local_head",
    "test_hacking.py::test_unmodified_script_keeps_its_fast_paths",
    "test_plots.py::test_learning_curves_match_logged_returns",
    "test_stops.py::test_resuming_a_finished_run_adds_nothing",
    "test_tracking.py::test_sweep_passes_track_in_one_group",
    "test_sweep.py::test_local_sweep_reports_failure_and_skips_finished_runs",
    "test_discrete.py::test_baseline_checkpoint_resume_and_evaluate",
    "test_stops.py::test_a_stop_after_the_final_checkpoint_lets_the_run_finish",
    "test_checkpoints.py::test_kill_9_during_the_iteration_copy_then_resume",
    "test_tracking.py::test_capture_video_records_training_and_changes_nothing",
    "test_checkpoints.py::test_stopping_a_run_is_one_line",
)


@pytest.fixture(autouse=True)
def no_stop_left_behind():
    """The stop bookkeeping a test leaves (an in-process run killed or stopped mid-way keeps its request) must not
    reach the next test's runs on the same worker."""
    yield
    from cascade_plumbing import runs

    runs.forget_stops()
    runs.STOPPED_BY.clear()
    runs.SAVED_AT_STOP.clear()


def pytest_configure(config):
    if getattr(config.option, "maxschedchunk", 0) is None:  # pytest-xdist's default: chunks of ~1/8 of the tests
        config.option.maxschedchunk = 1


def pytest_collection_modifyitems(config, items):
    if not getattr(config.option, "numprocesses", None):  # one process (tests/mutations.py's `-x` runs): the
        return  # order the tests were asked for, quickest reference tests first, so the first failure names them

    def rank(item):
        name = item.nodeid.split("/")[-1]
        return next((i for i, prefix in enumerate(LONG_FIRST) if name.startswith(prefix)), len(LONG_FIRST))

    items.sort(key=rank)  # stable: the others keep pytest's order (module fixtures built once per worker)
