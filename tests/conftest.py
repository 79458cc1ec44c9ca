"""Shared fixtures: small models with known closed forms."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import pytest
import torch

import difffilter as df

if os.environ.get("PYTEST_XDIST_WORKER"):
    # `make test` runs a worker per CPU (pytest-xdist): each on one intra-op thread, and so
    # the command lines its tests start, or two workers of two threads on two cores wait on
    # each other's threads (the LFC calibration: 629 s against 16 s)
    os.environ["OMP_NUM_THREADS"] = "1"
    torch.set_num_threads(1)

# Lightning attaches a stderr log handler when it is first imported; the command lines now
# import it only when a command needs it, so import it here, at collection, or the handler
# would hold the stream one test captured and fail on the next ("I/O operation on closed file")
import difffilter.train.lightning_cli  # noqa: E402, F401

#: The ``slow`` group (``pytest -m slow``; ``make test-slow``; CI runs it): end-to-end runs
#: of the command lines and trainings, multi-process runs, and statistical checks over many
#: Monte Carlo runs, each taking seconds to tens of seconds. ``make test`` runs the rest
#: (``-m "not slow"``). A file name marks every test of the file (their module fixtures are
#: the cost), ``file::test`` one test with all its parameters.
SLOW = (
    # whole files: a module fixture simulates or trains for tens of seconds
    "test_lfc_acceptance.py", "test_lfc_eval.py", "test_stealthy.py", "test_lfc_train.py",
    "test_four_tank_eval.py", "test_eval_devices.py", "test_docs_your_own_plant.py",
    "test_user_plants.py", "test_watermark.py", "test_train_logging.py", "test_sweep.py",
    "test_metrics_schema.py", "test_robustness.py", "test_shipped_card_checks.py",
    # single tests
    "test_adversarial.py::test_an_adversarial_fit_crafts_after_the_first_validation_and_logs_it",
    "test_calibrate_checkpoint.py::test_a_calibrated_lfc_checkpoint_alarms_at_its_threshold_on_its_head",
    "test_confirm.py::test_the_lfc_entry_scores_the_confirmed_probability_under_its_own_name",
    "test_calibration.py::test_every_detector_meets_the_target_false_alarm_rate_on_fresh_attack_free_runs",
    "test_gradients.py::test_optimal_transport_resampling_gradient_is_close",
    "test_gradients.py::test_soft_resampling_gradient_is_close",
    "test_gradients.py::test_stop_gradient_resampling_gives_consistent_gradient",
    "test_learned_estimator.py::test_ekf_trainer_learns_the_attack_and_its_export_evaluates_as_pf_nn_ekf",
    "test_learned_estimator.py::test_task_fit_export_and_evaluate_round_trip",
    "test_particle.py::test_every_resampler_gives_a_consistent_filter",
    "test_particle.py::test_pf_log_likelihood_error_shrinks_with_particles",
    "test_particle.py::test_pf_log_likelihood_within_three_standard_errors_of_kf",
    "test_step_objects.py::test_every_module_imports_alone",
    "test_kalman.py::test_gradcheck_kf_log_likelihood_wrt_F_Q_R",
    "test_particle.py::test_pf_means_agree_with_kf_within_monte_carlo_error",
    "test_hand_checks_internals.py::test_watermark_thresholds_come_from_the_calibration_seeds_runs",
    "test_calibrate_checkpoint.py::test_calibrate_sets_the_restart_it_runs_and_chooses_the_threshold_with",
    "test_acceptance.py::test_a_calibrated_report_judges_its_learned_estimator_against_the_best_analytic",
    "test_calibration.py::test_a_fingerprint_is_the_same_in_every_process",
    "test_plugin_scenarios.py::test_difffilter_eval_runs_a_scenario_of_ones_own",
    "test_plugin_scenarios.py::test_both_command_lines_take_scenario_as_an_option",
    "test_learned_cards_mutants.py::test_calibrate_keeps_the_cards_restart_and_confirm_and_counts_strict_exceedances",
    "test_learned_cards_mutants.py::test_calibrate_off_on_the_command_line_removes_restart_and_confirm_and_spares_the_source",
    "test_attacks_schedules_watermark_mutants.py::test_watermark_study_rows_against_their_definitions",
    "test_train_cli_resume_mutants.py::test_a_fit_leaves_its_run_folder_as_documented",
    "test_train_cli_resume_mutants.py::test_a_resumed_run_trains_the_uninterrupted_runs_weights_in_its_own_folder",
    "test_train_cli_resume_mutants.py::test_validate_of_a_resumed_runs_config_logs_apart_and_writes_config_validate",
    # end-to-end fits and resumes, a many-run statistic and a failing command line: 5-8 s
    # each, the five longest of make test on 2026-12-03
    "test_resume_settings.py::test_a_run_with_a_setting_of_its_own_resumes_only_with_it",
    "test_resume_settings.py::test_a_checkpoint_given_other_model_settings_is_refused_and_its_own_resume",
    "test_consistency.py::test_whiteness_under_packet_loss_counts_the_pairs_that_arrived",
    "test_hand_checks_cli.py::test_an_added_estimator_that_does_not_run_is_named_on_stderr",
    "test_threats_drawn.py::test_the_card_counts_the_threats_the_selected_weights_met_and_a_resume_counts_on",
    # 2 s or more each in make test on 2026-12-08 (its quiet pytest 139 s against the 2
    # minutes of `make test`): fresh processes, command lines, studies, fits and resumes,
    # and three numerical searches; 70 s of test time, 35 s of make test's
    "test_plant_match.py::test_a_module_plant_edited_after_training_is_named_by_its_fingerprint",
    "test_plant_match.py::test_the_scenario_file_digest_covers_the_python_code_the_file_names",
    "test_report_cli_findings.py::test_a_robustness_study_to_its_end_keeps_a_stopped_evaluations_marker_and_record",
    "test_report_cli_findings.py::test_each_kind_of_run_into_out_clears_only_its_own_incomplete_md",
    "test_sweep_cache_safety.py::test_an_interrupt_while_the_totals_are_saved_leaves_no_other_studys_totals",
    "test_adversarial.py::test_a_crafting_between_validations_crafts_under_the_current_networks_threshold",
    "test_adversarial_options_trial_findings.py::test_no_crafting_runs_under_a_threshold_no_one_chose",
    "test_lossy_control.py::test_an_uncontrollable_mode_on_the_unit_circle_is_named_as_such_at_rate_one",
    "test_lossy_control.py::test_sinopolis_example_has_a_critical_interval",
    "test_docs_offline_analysis.py::test_the_offline_analysis_snippet_prints_and_computes_what_the_page_says",
    "test_eval_write_safety.py::test_a_full_disk_under_ulimit_keeps_the_earlier_metrics",
    "test_api_fuzz_findings.py::test_a_model_of_one_noise_covariance_per_run_simulates_each_runs_noise",
    "test_resume_settings.py::test_a_threat_distribution_in_another_order_is_another_run",
    "test_resume_settings.py::test_a_run_resumed_after_an_interrupted_epoch_draws_each_point_once",
    "test_step_objects.py::test_one_ekf_object_steps_two_threads_carries_as_one_thread_does",
    "test_kf_online_trial_findings.py::test_a_restored_schedule_sees_the_first_assignment_of_a_new_process",
    "test_pipeline_new_plant.py::test_every_generic_estimator_runs_on_a_new_nonlinear_plant",
    "test_trial163_findings.py::test_a_resume_after_an_epoch_that_did_not_improve_keeps_that_epochs_points",
    "test_float32_trial_findings.py::test_a_float32_robot_study_is_reported",
    "test_float32_trial_findings.py::test_a_float32_tracking_study_is_reported",
    "test_hand_checks_families.py::test_lfc_network_score_is_its_estimate_over_the_spread_on_runs_of_its_own",
    "test_sigterm.py::test_a_terminated_fit_exits_143_keeps_last_ckpt_and_resumes",
    "test_particle_smoother.py::test_the_smoother_converges_to_the_rts_smoother_on_a_linear_model",
    # single parameters (the log-domain yardstick's; the default kernel method's stay fast)
    "test_resampling.py::test_ot_gradient_matches_finite_differences[particles-log]",
    "test_resampling.py::test_ot_gradient_matches_finite_differences[log_weights-log]",
)  # fmt: skip


def slow_name(nodeid: str) -> tuple[str, bool]:
    """``(file.py::test[parameters], slow)`` of a test's node id: its name as SLOW names
    tests, and whether SLOW lists its file, its test or its parameters."""
    # the folder cut before the first "::" (a parameter holding a path, "[{tmp}/vdp.yaml]",
    # had been cut instead, and its file's tests ran in make test though the file is listed)
    folder_file, sep, rest = nodeid.partition("::")
    named = folder_file.rsplit("/", 1)[-1] + sep + rest
    path = named.split("[")[0]  # file.py::test, parameters dropped
    return named, path.split("::")[0] in SLOW or path in SLOW or named in SLOW


def pytest_collection_modifyitems(config, items):
    collected = set()
    for item in items:
        named, slow = slow_name(item.nodeid)
        collected.add(named)
        if slow:
            item.add_marker(pytest.mark.slow)
    # an entry must name a file, test or parameter that exists (a renamed one would
    # otherwise move its tests back into the fast group unnoticed): its file on disk, and,
    # where whole files were collected (no node id asked for: `pytest file::test` collects
    # that test alone, and the file's other entries had read as missing: a review), its
    # test where its file was collected, its parameter where its test was
    functions = {named.split("[")[0] for named in collected}
    files = {named.split("::")[0] for named in collected}
    here = Path(__file__).parent
    whole_files = not any("::" in str(arg) for arg in config.args)
    stale = [e for e in SLOW
             if not (here / e.split("::")[0]).is_file()
             or (whole_files and "::" in e and "[" not in e
                 and e.split("::")[0] in files and e not in functions)
             or (whole_files and "[" in e and e.split("[")[0] in functions
                 and e not in collected)]  # fmt: skip
    if stale:
        raise pytest.UsageError(
            f"tests/conftest.py SLOW names files, tests or parameters that do not exist: {stale}"
        )


@contextlib.contextmanager
def registry_copy():
    """The scenario registry, loaded, then replaced by a copy while the block runs: what is
    registered in it leaves with it (for a module's fixture; a test's own:
    ``isolated_registry``). (A copy taken before the registry was loaded would receive the
    built-in scenarios and take them away with it, leaving the real registry empty but
    marked loaded for every later test of the process.)"""
    from difffilter.models import registry

    registry.names()
    with pytest.MonkeyPatch.context() as patch:
        for table in ("_REGISTRY", "_ORIGINS", "_FILES", "_CALLED"):
            patch.setattr(registry, table, dict(getattr(registry, table)))
        yield registry


@pytest.fixture
def isolated_registry():
    """The scenario registry as :func:`registry_copy` gives it, for this test."""
    with registry_copy() as registry:
        yield registry


@pytest.fixture(scope="session", autouse=True)
def _calibration_cache(tmp_path_factory):
    """Calibrations cached on disk go to a folder of this test session, not the user's."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("DIFFFILTER_CACHE", str(tmp_path_factory.mktemp("calibration-cache")))
        yield


def constant_velocity(
    dtype=torch.float64, q: float = 0.1, r: float = 0.5, with_input: bool = False
):
    """2-D constant-velocity model (tracking paper, eqs 16–17) with position measurements."""
    T = 1.0
    F = torch.tensor([[1, T, 0, 0], [0, 1, 0, 0], [0, 0, 1, T], [0, 0, 0, 1.0]], dtype=dtype)
    block = torch.tensor([[T**3 / 3, T**2 / 2], [T**2 / 2, T]], dtype=dtype)
    Q = q * torch.block_diag(block, block)
    H = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1, 0]], dtype=dtype)
    R = r * torch.eye(2, dtype=dtype) + 0.1 * r * torch.tensor([[0.0, 1], [1, 0]], dtype=dtype)
    B = torch.tensor([[0.5], [1.0], [0.2], [-0.3]], dtype=dtype) if with_input else None
    return df.LinearGaussianModel(
        F, H, Q, R, torch.tensor([0.0, 1, 0, -1], dtype=dtype), torch.eye(4, dtype=dtype), B=B
    )


@pytest.fixture
def cv_model():
    return constant_velocity()


@pytest.fixture
def generator():
    return torch.Generator().manual_seed(1234)


def online_pair(kind: str, num_particles: int = 10):
    """``(model, estimator, carry)``: a 2-state float64 linear model, a KF, EKF or particle
    filter (``kind``: ``"kf"``, ``"ekf"``, ``"pf"``) and its carry from ``init`` (the PF's
    with a generator of its own), for the online-step tests."""
    import difffilter as df

    F64 = torch.float64
    eye = torch.eye(2, dtype=F64)
    model = df.LinearGaussianModel(
        0.9 * eye, eye, 0.1 * eye, 0.2 * eye, torch.zeros(2, dtype=F64), eye
    )
    estimator = {"kf": df.KalmanFilter(), "ekf": df.ExtendedKalmanFilter(),
                 "pf": df.ParticleFilter(num_particles)}[kind]  # fmt: skip
    if kind == "pf":
        return model, estimator, estimator.init(model, (), torch.Generator().manual_seed(0))
    return model, estimator, estimator.init(model, ())


def small_four_tank_fit(max_epochs: int) -> list[str]:
    """``difffilter-train fit`` options of a four-tank training of a few seconds: three
    batches of two runs of 20 steps an epoch, a network of 4 hidden units, 20 particles."""
    config = Path(__file__).resolve().parents[1] / "train" / "configs" / "four_tank.yaml"
    return ["--config", str(config), "--data.init_args.batch_size=2",
            "--data.init_args.batches_per_epoch=3", "--data.init_args.val_runs=4",
            "--data.init_args.steps=20", "--model.init_args.hidden=4",
            "--model.init_args.num_particles=20", "--trainer.log_every_n_steps=1",
            f"--trainer.max_epochs={max_epochs}"]  # fmt: skip


def session_scalars(logdir) -> dict[str, list[float]]:
    """The HPARAMS session scalars under ``logdir`` (``eval.tensorboard.add_session``
    writes them as double-precision tensors: ``{tag: [values]}``, as TensorBoard reads them)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    from tensorboard.util import tensor_util

    events = EventAccumulator(str(logdir))
    events.Reload()
    return {
        tag: [float(tensor_util.make_ndarray(e.tensor_proto)) for e in events.Tensors(tag)]
        for tag in events.Tags()["tensors"]
        if not tag.startswith("_hparams_/")
    }
