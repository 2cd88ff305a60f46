import os
import shutil
import tempfile

# The suite compiles hundreds of small XLA programs that then run for milliseconds, so compile
# time dominates it: build them without LLVM's optimisation passes (the whole suite without
# coverage on two cores: 450 s, against 777 s at level 3; level 1 was slower still on the
# modules tried; the arithmetic is the same, XLA's fast-math stays off). Set before JAX starts
# its backend, and inherited by the notebook kernels and the subprocess tests.
# The solvers compile faster still with XLA:CPU's older element-wise emitters, which the package
# uses for its own compilations (cdra_jax.compilation); setting them here gives the tests that
# call jax.jit directly the same configuration. tests/test_compilation.py compares the solvers
# under both emitters explicitly. Without LLVM's optimisation passes, splitting each program's
# code generation over threads costs more than it saves (the two xdist workers already hold
# both cores): one part per program made four compile-heavy modules 13 % quicker (89.8 / 84.5 s
# against 104.9 / 96.6 s, two interleaved runs each).
# Two of XLA's HLO passes are left out: the HLO verifier (`hlo-verifier`), which checks XLA's own
# invariants after every pass, and the while-loop simplifier (`simplify-while-loops`), which
# works out the trip count of a loop by copying the loop's computations, again at each round of
# the simplification fix point (the solvers' loops are nested). A CPU profile of compiling the
# vmapped paper and LM solvers with these options (perf) put 3.6 % of the process in the
# simplifier; without it the LM solver's XLA compile took 1.08 s against 1.27 s (medians of four,
# alternated). Neither changes a result: the frames and iteration counts of the paper, weighted
# and LM solvers, float64 and float32, over 64 trials were bitwise equal without them. (Leaving
# out loop-invariant code motion as well moved float32 rounding enough to change where a float32
# LM solve stops.) Whole suite under coverage.py's tracer, one run each: 675 s of CPU without
# the verifier, 711 s with it. XLA ignores a pass name it does not know: the names are those of
# the passes' `name()`.
_FLAGS = (
    "--xla_backend_optimization_level=0",
    "--xla_cpu_use_fusion_emitters=false",
    "--xla_cpu_parallel_codegen_split_count=1",
    "--xla_disable_hlo_passes=hlo-verifier,simplify-while-loops",
)
for _flag in _FLAGS:
    if _flag.split("=")[0] not in os.environ.get("XLA_FLAGS", ""):
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + _flag).strip()

# numpy's OpenBLAS at one thread per process: the two xdist workers already hold both cores,
# and OpenBLAS threads that wait for a core by spinning made the many small SVDs of the
# diagnosis' statistics cost several times their work (test_diagnosis.py: 54-65 s of CPU against
# 105-122 s, alternated, on a loaded machine). Set here, in the controller, before it starts the
# workers and the subprocesses, which inherit it (in a run without xdist, a plugin may have
# imported numpy first: set it in the shell there).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

# One on-disk XLA compilation cache for the whole run, shared by the xdist workers, the modules
# (whose in-memory caches are dropped after each one, below) and the subprocesses (notebook
# kernels, two-device scripts), which inherit the environment: a program that another worker
# or module compiled is loaded instead of compiled again. Made fresh for each run (by the
# controller, before it starts the workers) and removed at its end (pytest_unconfigure); a
# JAX_COMPILATION_CACHE_DIR of your own is used as it is and kept.
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    os.environ["JAX_COMPILATION_CACHE_DIR"] = tempfile.mkdtemp(prefix="cdra-jax-test-xla-cache-")
    os.environ["CDRA_JAX_TEST_OWN_CACHE"] = os.environ["JAX_COMPILATION_CACHE_DIR"]
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")

import ctypes  # noqa: E402
import gc  # noqa: E402

import jax  # noqa: E402
import pytest  # noqa: E402
from _memory import resident_bytes  # noqa: E402

from cdra_jax.compilation import GC_THRESHOLDS  # noqa: E402

jax.config.update("jax_enable_x64", True)

# Tracing and lowering create millions of short-lived Python objects, and with CPython's
# default thresholds (700, 10, 10) the cycle collector runs every few hundred of them, each time
# scanning the young objects (and often the old ones, the traces and programs held in JAX's
# caches). Rarer collections: tracing and lowering the vmapped paper and LM solvers and a
# simulation took 1.68-1.77 s of CPU against 2.03-2.08 s (alternated). The collection that
# frees the compiled programs is explicit (_drop_compiled_programs_above).
gc.set_threshold(*GC_THRESHOLDS)


def pytest_collection_finish(session):
    """Move every object alive once the tests are collected (the imported modules: JAX, numpy,
    scipy, matplotlib, the package, the test modules; about 200,000 objects) to the cycle
    collector's permanent generation (``gc.freeze``), so that the full collections of the run
    (the explicit one after each drop of the compiled programs, pytest's at the end) no longer
    scan them. They live to the end of the process anyway; reference counting still frees what
    is not in a cycle. On three modules (calibration, robust, workflows; one process) the
    collections took 1.61-1.71 s in all against 2.36-2.39 s (``gc.callbacks``, alternated)."""
    gc.freeze()


_RSS_AFTER_LAST_DROP = [0]
"""This worker's resident memory right after it last dropped its programs (bytes)."""

_RSS_REGROWTH_BYTES = 500_000_000
"""After a test, a worker drops its programs again only once its memory has grown this much since
the last drop: memory that the allocator keeps after a drop must not make every test drop (and
trace everything again), which made the suite 40 % slower. (After a module it drops whenever it
holds more than :data:`_RSS_LIMIT_BYTES`: keeping programs across modules doubled the peak.)"""


def _return_freed_memory() -> None:
    """Hand the memory that the C allocator holds free back to the system (glibc's
    ``malloc_trim``; nothing elsewhere), so that the resident size measures what the worker
    still uses: glibc otherwise keeps the pages of the programs that JAX freed, and the
    resident size never falls."""
    try:
        ctypes.CDLL(None).malloc_trim(0)
    except (OSError, AttributeError):
        pass


def _drop_compiled_programs_above(limit: int, regrowth: int = 0) -> None:
    """Drop JAX's compiled programs and traces when this worker holds more than ``limit``
    bytes and has grown by ``regrowth`` since its last drop (never with
    ``CDRA_TEST_KEEP_CACHES=1``). Memory already freed is handed back first: if that brings the
    worker below the bounds, the programs stay."""
    if os.environ.get("CDRA_TEST_KEEP_CACHES") == "1":
        return
    bound = max(limit, _RSS_AFTER_LAST_DROP[0] + regrowth)
    if resident_bytes() <= bound:
        return
    _return_freed_memory()
    if resident_bytes() > bound:
        jax.clear_caches()
        gc.collect()
        _return_freed_memory()
        _RSS_AFTER_LAST_DROP[0] = resident_bytes()


_RSS_LIMIT_BYTES = 1_200_000_000
"""A worker drops its compiled programs after a module once its resident memory exceeds this
(measured after the freed memory is handed back: about 0.4-0.6 GB remain after a drop, so the
programs of the last module or two stay for the next; on a subset of twelve modules 3.5 % less
CPU and a peak of 1.5 GB against 2.1 GB with 700 MB and no hand-back)."""


@pytest.fixture(scope="module", autouse=True)
def _free_compiled_programs_after_each_module():
    """Drop JAX's compiled programs and traces after a test module once the worker holds more
    than :data:`_RSS_LIMIT_BYTES`, bounding memory.

    Without it, one xdist worker keeps every executable that the modules it ran have compiled
    (peak RSS ~6 GB for the whole suite). Dropping them only when memory is high keeps the
    programs that the next modules share (tracing them again is Python work); the on-disk cache
    above makes the recompilation cheap.
    """
    yield
    _drop_compiled_programs_above(_RSS_LIMIT_BYTES)


_RSS_TEST_LIMIT_BYTES = 1_500_000_000
"""A worker drops its compiled programs after any test once its resident memory exceeds this."""


@pytest.fixture(autouse=True)
def _free_compiled_programs_when_memory_is_high(request):
    """Within a module, drop the compiled programs after a test once the worker holds more than
    :data:`_RSS_TEST_LIMIT_BYTES`: modules of random arms or imported arms compile programs that
    no later test reuses (one such module otherwise reached 3.4 GB), and the 3 GB budget of the
    suite is per run, not per module. Not within a module marked ``keep_programs``, whose tests
    share their programs (the diagnosis': the candidates' features of one arm, about 5 s to
    compile and 1 s to trace, about 400 MB for the whole module)."""
    yield
    if request.node.get_closest_marker("keep_programs") is None:
        _drop_compiled_programs_above(_RSS_TEST_LIMIT_BYTES, _RSS_REGROWTH_BYTES)


@pytest.fixture(scope="session")
def cdra():
    from cdra_jax import default_arm

    return default_arm()


# A UR5-like 6R industrial arm as the same modular chain: six revolute modules about their
# local z axes with the fixed (Denavit-Hartenberg) transforms Tz(d) Tx(a) Rx(alpha) between
# them, lengths in mm. The tool frame is the UR5 flange (DH row 6).
UR5_TOML = """
name = "ur5"
description = "UR5-like 6R arm: DH rows as fixed transforms between revolute modules"

[[frames]]
name = "base"
xyz = [0.0, 0.0, 0.0]
rotvec = [0.0, 0.0, 0.0]

[[frames]]
name = "link1"
xyz = [0.0, 0.0, 89.159]
rotvec = [1.5707963267948966, 0.0, 0.0]

[[frames]]
name = "link2"
xyz = [-425.0, 0.0, 0.0]
rotvec = [0.0, 0.0, 0.0]

[[frames]]
name = "link3"
xyz = [-392.25, 0.0, 0.0]
rotvec = [0.0, 0.0, 0.0]

[[frames]]
name = "link4"
xyz = [0.0, 0.0, 109.15]
rotvec = [1.5707963267948966, 0.0, 0.0]

[[frames]]
name = "link5"
xyz = [0.0, 0.0, 94.65]
rotvec = [-1.5707963267948966, 0.0, 0.0]

[[frames]]
name = "tool"
xyz = [0.0, 0.0, 82.3]
rotvec = [0.0, 0.0, 0.0]
""" + "".join(
    f"""
[[modules]]
name = "joint{i}"
kind = "revolute"
axis = [0.0, 0.0, 1.0]
limits = [[-3.0, 3.0]]
"""
    for i in range(1, 7)
)


@pytest.fixture(scope="session")
def ur5():
    from cdra_jax.io import loads_model

    return loads_model(UR5_TOML, source="<tests/conftest.py UR5_TOML>")


# Each test module runs on one worker (`--dist loadfile`, pyproject.toml), so that its tests share
# the programs they compile (the same solvers at the same shapes): with the tests dealt out one by
# one, a module's tests were spread over both workers, each tracing and compiling their programs,
# and the suite took 15 % longer (1,000 against 870 worker-seconds). The modules are handed out
# longest first (every module of 5 s or more, by its measured time in a whole run), so that
# with `-n 2` the two workers end on short modules instead of one finishing a long one alone
# (`--no-loadscope-reorder`: xdist's own order is by the number of tests). The others, of a few
# seconds each, follow in the order of collection.
_LONG_FIRST = (
    "tests/test_diagnosis.py",
    "tests/test_notebooks.py",
    "tests/test_nullspace.py",
    "tests/test_calibration.py",
    "tests/test_sweeps.py",
    "tests/test_float32_and_noise_checks.py",
    "tests/test_implicit_derivatives.py",
    "tests/test_workflows.py",
    "tests/test_markers.py",
    "tests/test_gravity_moments.py",
    "tests/test_calibration_kernels.py",
    "tests/test_model_effects.py",
    "tests/test_robust.py",
    "tests/test_benchmark_baselines.py",
    "tests/test_reproduction.py",
    "tests/test_sweep_processes.py",
    "tests/test_fuzz.py",
    "tests/test_cli_robust.py",
    "tests/test_cli.py",
    "tests/test_batching.py",
    "tests/test_hostile_input.py",
    "tests/test_physics.py",
    "tests/test_compilation.py",
    "tests/test_modules_tension.py",
    "tests/test_uncertainty.py",
    "tests/test_pose_selection.py",
    "tests/test_concealed_generator.py",
    "tests/test_modules_cables.py",
    "tests/test_optimistix_lm.py",
)


# The quick loop, `python -m pytest -q -n 2 -m "not slow"` (about a minute on two cores), skips
# the tests marked slow: those marked in their files, and these, marked here because each costs
# a second or more of CPU (mostly compiling solvers; measured per test on the full suite). Most
# modules keep a cheap test in the quick loop. The default run (CI) runs them all.
_SLOW: dict[str, tuple[str, ...]] = {
    "tests/test_benchmark_baselines.py": (
        "test_baseline_calibrations_agree_with_the_paper_solver",
    ),
    "tests/test_calibration.py": (
        "test_noisy_solution_is_stationary",
        "test_metric_gradients_are_finite_at_an_exact_fit_and_exact_elsewhere",
        "test_nan_in_measurements_raises_with_throw",
        "test_noise_free_recovery_cdra",
        "test_residual_gradients",
        "test_underdetermined_gives_the_minimum_norm_answer",
        "test_bad_shapes_raise",
    ),
    "tests/test_calibration_kernels.py": (
        "test_linearise_is_the_stacked_system",
        "test_lm_first_step_is_the_gauss_newton_step",
        "test_lm_jacobian_is_the_derivative_of_the_residual",
        "test_whiten_is_model_whitening",
    ),
    "tests/test_cli.py": (
        "test_implausibly_large_identified_errors_warn",
        "test_not_converged_exits_3_and_still_writes_the_result",
        "test_simulate_cables_then_calibrate",
        "test_simulate_then_calibrate_recovers_the_preset_errors",
        "test_simulate_writes_csv_with_preset_errors_in_comments",
        "test_explicit_model_file_gives_the_same_simulation_as_the_default",
        "test_outputs_are_not_overwritten_without_force",
    ),
    "tests/test_cli_robust.py": (
        "test_least_squares_result_has_unit_weights_and_flags",
        "test_warning_rows_give_warning_lines_and_write_the_result",
        "test_cauchy_flags_the_corrupted_poses_in_summary_and_json",
        "test_reject_outliers_refits_without_the_flagged_poses",
        "test_degenerate_pose_sets_warn_and_give_the_min_norm_answer",
        "test_failure_modes_give_one_error_line_and_exit_1",
    ),
    "tests/test_compilation.py": ("test_options_change_no_result_of_the_solvers",),
    "tests/test_concealed_generator.py": (
        "test_twin_shares_poses_errors_and_noise",
        "test_every_effect_at_zero_size_is_the_geometric_model",
        "test_size_calibration_hits_the_requested_unabsorbed_rms",
        "test_columns_are_the_same_for_every_effect",
        "test_harness_scores_a_perfect_and_a_blind_stand_in",
        "test_out_of_library_effects_are_not_absorbed",
    ),
    "tests/test_degenerate.py": (
        "test_identical_poses_keep_six_parameters_and_name_the_other_eighteen",
        "test_elbow_never_moved_loses_six_more_directions",
        "test_fewer_poses_than_the_lower_bound_stop_or_go_min_norm",
    ),
    "tests/test_diagnosis.py": (
        "test_clean_recordings_give_none",
        "test_injected_effect_is_found_where_it_is",
        "test_a_richer_form_is_refitted_and_reaches_the_noise_floor",
        "test_uniform_length_scale_is_absorbed",
        "test_out_of_library_distortion_is_unattributed",
        "test_without_noise_values_the_noise_is_estimated",
        "test_without_noise_values_clean_recordings_give_none",
        "test_exactly_repeated_exact_poses_give_none",
        "test_cli_end_to_end",
        "test_point_data_clean_give_none_and_an_injected_effect_is_found_where_it_is",
        "test_point_data_through_the_cli",
        "test_the_refit_model_predicts_poses_the_diagnosis_never_saw",
        "test_a_model_with_the_found_effect_explains_new_recordings",
        "test_a_physically_impossible_estimate_is_never_reported",
        "test_a_candidate_that_fails_numerically_is_marked_failed_and_the_diagnosis_goes_on",
        "test_the_verdict_does_not_depend_on_the_noise_values",
        "test_a_shape_the_vocabulary_lacks_is_unattributed_where_it_lives_without_noise_values",
        "test_bad_inputs_raise_clear_errors",
        "test_a_misfit_that_changes_with_time_is_placed_at_the_frame_whose_time_probe_explains_it",
        "test_refit_columns_are_those_of_the_full_jacobian",
    ),
    "tests/test_float32_and_noise_checks.py": (
        "test_explicit_tolerances_still_apply_in_float32",
        "test_float32_solves_agree_with_float64",
        "test_float32_solves_stay_float32_and_converge_with_the_default_tolerances",
        "test_float64_default_tolerance_is_the_old_one_bitwise",
        "test_robust_rejection_of_a_failed_trial_outside_jit_reports_nonfinite",
        "test_per_pose_noise_of_the_wrong_shape_raises_naming_the_field",
    ),
    "tests/test_fuzz.py": (
        "test_pose_selection_picks_distinct_poses_or_names_the_bad_state",
        "test_random_arms_have_finite_kinematics_identifiability_and_round_trip",
        "test_solvers_never_report_success_with_nan",
        "test_sweep_rows_are_finite_when_converged",
    ),
    "tests/test_gravity_moments.py": (
        "test_lumped_moments_are_the_identifiable_combinations_of_the_statics",
        "test_bending_with_masses_is_a_combination_of_the_lumped_columns",
        "test_a_lumped_effect_round_trips_through_the_model_file",
    ),
    "tests/test_hostile_input.py": (
        "test_out_symlink_is_written_through",
        "test_a_noise_std_of_1e_300_is_refused",
        "test_force_onto_a_folder_is_refused",
        "test_text_in_a_number_cell_names_file_line_and_column",
        "test_bad_result_and_frame_error_files_name_the_file",
        "test_force_onto_a_fifo_is_refused_and_the_fifo_stays",
        "test_malformed_model_files_name_the_key",
        "test_random_cell_values_are_read_or_named",
        "test_force_onto_dev_null_is_refused_and_it_stays_a_device",
        "test_max_iterations_beyond_the_machine_integers_is_refused",
    ),
    "tests/test_implicit_derivatives.py": (
        "test_gradients_under_vmap_and_at_an_exact_fit",
        "test_lm_derivative_is_that_of_the_least_squares_optimum",
        "test_paper_solver_derivative",
        "test_weighted_solver_derivative",
    ),
    "tests/test_io_measurements.py": (
        "test_cable_length_columns_give_the_module_state",
        "test_bad_cable_lengths_name_row_and_column",
    ),
    "tests/test_io_results.py": ("test_structure_and_iteration_indexing",),
    "tests/test_lie.py": (
        "test_log_jacobians",
        "test_rotation_angle_gradient_is_finite_at_identity",
    ),
    "tests/test_markers.py": (
        "test_cli_simulate_calibrate_model_out_validate_on_markers",
        "test_the_guard_fires_when_an_unweighted_fit_is_worse_than_nominal",
        "test_plan_poses_for_a_model_measured_by_markers",
        "test_a_gross_point_error_is_flagged_and_down_weighted",
        "test_diagnose_calibrates_rough_markers_before_it_looks_for_missing_physics",
        "test_markers_with_occlusions_recover_the_arm_from_a_far_device_frame",
        "test_noise_scales_are_estimated_and_clean_data_are_not_flagged",
        "test_tool_positions_only_recover_what_points_can_see",
    ),
    "tests/test_model_effects.py": (
        "test_calibrate_refines_the_effects_with_the_frames",
        "test_calibrate_with_effects_from_points",
        "test_calibrate_with_effects_refuses_rough_markers_and_robust_losses",
        "test_sweep_refuses_and_plan_poses_notes_the_effects",
        "test_a_load_dependent_effect_is_refined_in_the_gauge",
        "test_validate_with_the_effects_reaches_the_noise_floor",
        "test_simulate_writes_the_effects_and_their_columns",
        "test_effects_need_their_columns",
        "test_model_tool_pose_without_effects_is_the_chain",
    ),
    "tests/test_modules_cable_data.py": (
        "test_wrong_column_count_and_impossible_rows_are_all_diagnosed",
        "test_states_from_exact_and_noisy_lengths",
        "test_bad_cable_data_names_the_row_and_the_column",
    ),
    "tests/test_modules_cables.py": (
        "test_forward_kinematics_from_noisy_lengths_reports_the_residual",
        "test_initial_guess_and_offsets",
        "test_forward_kinematics_round_trip_over_the_workspace",
        "test_forward_kinematics_under_vmap_equals_a_loop",
        "test_prismatic_module_round_trip",
        "test_inconsistent_and_bad_lengths_get_result_codes",
    ),
    "tests/test_modules_self_calibration.py": (
        "test_recovery_with_length_noise_is_within_its_predicted_uncertainty",
        "test_identifiability_report_names_the_gauge_freedoms",
        "test_noise_free_recovery_of_spherical_modules",
        "test_calibrated_module_goes_into_the_arm_and_the_model_file",
    ),
    "tests/test_modules_statics.py": (
        "test_distribution_is_the_minimum_norm_one",
        "test_holding_tensions_are_in_equilibrium_and_above_the_floor",
        "test_infeasible_load_is_reported_not_raised",
    ),
    "tests/test_modules_tension.py": (
        "test_arm_closure_gives_the_verdicts_of_tension_closure_and_hull_margin",
        "test_closure_of_random_planar_and_spatial_matrices",
        "test_closure_verdicts_and_margins_agree_with_scipy",
        "test_sample_poses_conditions_only_the_modules_with_cables",
        "test_sampler_raises_when_too_few_states_are_feasible",
        "test_sampler_returns_only_feasible_states_within_the_limits",
    ),
    "tests/test_nullspace.py": (
        "test_null_basis_is_the_svd_null_space_on_random_arms",
        "test_null_space_solve_is_the_pseudo_inverse_step",
        "test_null_space_solve_flags_data_rank_deficiency",
    ),
    "tests/test_optimistix_lm.py": ("test_optimistix_lm_reaches_the_fast_solvers_minimum",),
    "tests/test_physics.py": (
        "test_refinements_are_richer_forms_of_a_tested_effect",
        "test_vocabulary_is_the_design_table",
        "test_zero_parameters_give_the_geometric_model_exactly",
        "test_backlash_and_drift_follow_their_auxiliaries",
        "test_bending_force_part_is_the_textbook_cantilever",
        "test_features_shapes_and_jacobians_finite",
        "test_single_candidate_pure_function_matches_the_stacked_features",
        "test_skip_reasons_name_what_is_missing",
        "test_only_periodic_series_name_a_coordinate_for_the_shape_check",
    ),
    "tests/test_plausibility.py": (
        "test_no_typo_warning_on_clean_simulated_files",
        "test_a_400_mm_typo_in_one_of_30_rows_is_named",
    ),
    "tests/test_pose_selection.py": (
        "test_exchange_reaches_a_swap_local_optimum",
        "test_tool_positions_used_for_whitening",
        "test_blocks_and_basis",
        "test_i_opt_reaches_a_swap_local_optimum_of_the_predicted_heldout_error",
        "test_o1_index_and_sampler",
        "test_plan_poses_cli",
        "test_selected_poses_predict_better_than_random",
        "test_unbounded_prediction_where_the_pool_identifies_too_little",
    ),
    "tests/test_reproduction.py": (
        "test_table_one_differences_lie_in_the_null_space",
        "test_convergence_within_six_iterations",
        "test_demo_writes_tables_and_figures",
        "test_noise_study_monotone_ish",
        "test_pose_repetition_gives_the_same_calibration",
        "test_rounding_bound_holds_for_random_roundings",
        "test_table_one_base_and_tool_exact",
        "test_table_one_null_coordinates_are_in_the_printed_basis",
        "test_table_one_papers_values_fit_to_their_rounding",
    ),
    "tests/test_robust.py": (
        "test_huber_solution_solves_the_reweighted_normal_equations",
        "test_noise_free_data_flag_nothing_and_recover_the_errors",
        "test_cauchy_without_noise_model_estimates_the_scale_by_mad",
        "test_huber_flags_exactly_the_corrupted_poses",
        "test_huber_keeps_the_accuracy_of_the_clean_fit",
        "test_least_squares_with_too_optimistic_noise_flags_most_poses_and_says_why",
        "test_reject_outliers_keeps_the_robust_fit_when_too_few_poses_remain",
        "test_reject_outliers_refits_least_squares_on_the_unflagged_poses",
        "test_errors_are_against_the_nominal_frames_and_histories_count_solves",
        "test_uncertainty_of_a_robust_fit_uses_its_final_weights",
    ),
    "tests/test_sweep_processes.py": (
        "test_two_local_processes_give_the_one_process_table",
        "test_a_process_that_never_connects_ends_the_wait",
    ),
    "tests/test_sweeps.py": (
        "test_chunking_does_not_change_trials",
        "test_run_sweep_accepts_numpy_integers_and_noise_models",
        "test_csv_round_trip_and_errors",
        "test_every_pose_a_sweep_draws_has_tension_closure",
        "test_table_layout",
        "test_cli_and_plot",
        "test_identifiable_projection_analytic_and_svd",
    ),
    "tests/test_uncertainty.py": (
        "test_covariance_is_pinv_of_whitened_information",
        "test_pose_covariance_matches_autodiff",
        "test_predicted_accuracy_gradients",
        "test_prediction_unbounded_where_the_poses_leave_directions_unidentified",
        "test_cramer_rao_bound",
    ),
    "tests/test_workflows.py": (
        "test_model_out_and_compare",
        "test_the_cli_keeps_compiled_programs_between_runs",
        "test_validate_cli_matches_the_function",
        "test_a_fit_worse_than_nominal_is_marked_untrusted",
        "test_an_interrupted_sweep_resumes_from_its_finished_chunks",
        "test_calibrate_cli_writes_the_figure",
        "test_calibrate_result_object",
        "test_calibrate_solver_names_are_those_of_sweep",
        "test_simulate_result_object",
        "test_sweep_prints_progress_lines_when_stderr_is_not_a_terminal",
        "test_validate_refuses_a_plan_without_measured_poses",
        "test_validate_reports_the_gain_on_held_out_poses",
    ),
}


# The extended checks: statistical acceptance checks at the scale of the benchmarks (every
# effect of the vocabulary found where it was hidden, verdicts stable under the noise values,
# random arms and effects), end-to-end reruns that repeat a cheaper test's path with another
# interruption or data kind, and the multi-process sweeps beyond the two-process one. They
# cost about a third of the suite's CPU, so the default run (the README's command and CI)
# leaves them out; `python -m pytest -q -n 2 --extended` runs the whole suite, them included.
_EXTENDED = (
    "tests/test_diagnosis.py::test_a_model_with_the_found_effect_explains_new_recordings",
    "tests/test_diagnosis.py::test_without_noise_values_the_noise_is_estimated",
    "tests/test_diagnosis.py::test_injected_effect_is_found_where_it_is[joint_compliance",
    "tests/test_diagnosis.py::test_injected_effect_is_found_where_it_is[thermal_drift",
    "tests/test_diagnosis.py::test_injected_effect_is_found_where_it_is[cable_scale",
    "tests/test_diagnosis.py::test_point_data_clean_give_none_and_an_injected_effect_is_found",
    "tests/test_diagnosis.py::test_clean_recordings_give_none[2]",
    "tests/test_diagnosis.py::test_clean_recordings_give_none[3]",
    "tests/test_gravity_moments.py::test_a_concealed_joint_compliance_is_found_without_masses",
    "tests/test_gravity_moments.py::test_random_arms_with_random_effects_never_crash",
    "tests/test_gravity_moments.py::test_simulate_calibrate_and_validate_honour_a_lumped_effect",
    "tests/test_gravity_moments.py::test_lumped_moments_are_the_identifiable_combinations_of_the_statics[0",
    "tests/test_gravity_moments.py::test_lumped_moments_are_the_identifiable_combinations_of_the_statics[1",
    "tests/test_gravity_moments.py::test_lumped_moments_are_the_identifiable_combinations_of_the_statics[2",
    "tests/test_markers.py::test_diagnose_calibrates_rough_markers_before_it_looks_for_missing_physics",
    "tests/test_sweep_processes.py::test_a_dead_worker_is_named_and_the_sweep_resumes",
    "tests/test_sweep_processes.py::test_processes_started_by_hand_give_the_same_table",
    "tests/test_hostile_input.py::test_sigterm_during_a_sweep_leaves_no_file_and_the_rerun_resumes",
    "tests/test_reproduction.py::test_pose_repetition_gives_the_same_calibration",
    "tests/test_reproduction.py::test_noise_study_monotone_ish",
    "tests/test_nullspace.py::test_random_arm_calibration_is_the_svd_solution[kinds1]",
)


def pytest_addoption(parser):
    parser.addoption(
        "--extended",
        action="store_true",
        help="also run the extended checks (tests/conftest.py _EXTENDED; about a third more CPU)",
    )


def _mark_slow(items):
    for item in items:
        path, _, name = item.nodeid.partition("::")
        if name.split("[")[0] in _SLOW.get(path, ()):
            item.add_marker(pytest.mark.slow)


@pytest.hookimpl(tryfirst=True)  # marks before the -m "not slow" deselection
def pytest_collection_modifyitems(config, items):
    _mark_slow(items)
    extended = [it for it in items if it.nodeid.startswith(_EXTENDED)]
    for item in extended:
        item.add_marker(pytest.mark.extended)
        item.add_marker(pytest.mark.slow)
    if extended and not config.getoption("--extended"):
        config.hook.pytest_deselected(items=extended)
        items[:] = [it for it in items if not it.nodeid.startswith(_EXTENDED)]

    def rank(item):
        for i, prefix in enumerate(_LONG_FIRST):
            if item.nodeid.startswith(prefix):
                return i
        return len(_LONG_FIRST)

    items.sort(key=rank)  # stable: the order within each module is kept


def pytest_unconfigure(config):
    own = os.environ.get("CDRA_JAX_TEST_OWN_CACHE")
    if own and not hasattr(config, "workerinput"):  # the controller (or a run without xdist)
        shutil.rmtree(own, ignore_errors=True)
