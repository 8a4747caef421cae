"""The tests marked ``reduction_order`` (applied in tests/conftest.py; not collected: no ``test_`` prefix).

`make test` runs the whole suite once, then only these a second time with other float reduction orders and
kernels (two threads, torch's portable non-SIMD kernels: ATEN_CPU_CAPABILITY=default, oneDNN at SSE4.1), as on
another CPU. Chosen by reading each test: it compares two computations of one quantity at a rounding-level
tolerance (``roundoff_tol``, machine epsilons, ≲ 1e-11 relative in float64, ≲ 1e-5 in float32) or exactly
(batched vs per sample, export vs eager, folded vs model, closed form vs autograd, library vs an independent
reference, threads vs serial, stored outputs of an older version), so its verdict can change with the
summation order or a vectorised sin/exp; or it asserts a rounding-level property (orthonormality, a residual
at the rounding level, an ordering that near-ties could swap). Not listed: tests with tolerances far above
rounding (trained-model quality, finite differences, float64 gradchecks at their default tolerances, the DDP
metrics at 1e-5 relative), exact equality of one computation run twice in one process (determinism, round
trips of files), error messages; the ablation grid's offset rows (a whole grid trained for an equality
that test_common_mode_offset_leaves_clarke_fk_unchanged checks at the model, in both passes); and the exports of
main's old files (test_legacy_checkpoints.py, test_export_entry.py: whether an old file still exports is no matter of
rounding, and their float32 exports are held to the export's 1e-5, as the exports that test_export.py,
test_compositional.py and test_hardware_deploy_export.py compare with the eager models in both passes).

`make test` runs the second pass in both of its processes, after their first-pass share: the modules of
:data:`BESIDE_THE_SLOW_TESTS` after the slow tests (marker ``second_pass_beside_slow``), the others after the rest,
so that the two processes end together. Any split is correct; this one balances the measured times. The second pass
of a test that exports a model (conftest.first_pass_export) runs the programs its first pass exported, so a module
whose tests export runs its second pass in the process of its first (the slow tests' or the rest's).

A listed name that no longer exists in its module is an error at collection (conftest.py), so a renamed test
cannot drop out of the second pass silently. New tests of the kinds above belong here.
"""
from __future__ import annotations

REDUCTION_ORDER: dict[str, tuple[str, ...]] = {
    "test_ablation.py": ("test_common_mode_offset_leaves_clarke_fk_unchanged",),
    "test_arm.py": (
        "test_panda_chain_is_the_urdf_to_round_off",
        "test_any_urdf_chain_matches_numpy",
        "test_whole_body_fk_matches_the_independent_chain",
        "test_the_variables_and_limits_stack_arm_then_robot",
        "test_pose_bank_seeds_are_the_nearest_samples",
        "test_a_position_only_robot_makes_a_position_only_whole_body",
    ),
    "test_arm_control.py": (
        "test_velocity_limits_and_frozen_variables",
        "test_decoupled_scheme_moves_the_arm_for_a_straight_robot_then_the_robot",
    ),
    "test_clarke.py": (
        "test_symmetric_clarke_matrix_closed_form",
        "test_symmetric_properties",
        "test_arbitrary_clarke_matrix_is_left_inverse_with_radii",
        "test_clarke_matrix_batched",
        "test_erratum1_identity_has_minus_sign",
        "test_erratum2_paper_length_is_wrong_for_arbitrary_angles",
        "test_erratum2_straight_length_only",
        "test_erratum3_encoder_matches_block_diagonal_map",
        "test_erratum4_unequal_radii_need_radius_ratio",
        "test_joint_space_maps_coupled_block_lower_triangular",
        "test_erratum1_minus_sign_with_library_matrices",
        "test_erratum2_paper_length_bias_is_exact_and_encoder_is_exact",
        "test_erratum2_five_random_angles_straight",
        "test_erratum3_type3_block_map_with_joint_radius_unlike_reference",
        "test_erratum4_unequal_radii_tip_pose",
    ),
    "test_compositional.py": (
        "test_composed_frames_equal_cc_kinematics",
        "test_strain_units_make_one_exact_map_for_every_segment_geometry",
        "test_a_twisting_segment_is_exact_only_when_rolled_first",
        "test_the_untrained_network_does_not_depend_on_a_rolled_segments_alpha",
        "test_the_roll_leaves_a_robot_that_does_not_twist_unchanged",
        "test_transfer_in_strain_units_runs_any_geometry",
        "test_old_metric_state_dict_loads",
        "test_batched_equals_per_sample_float32",
        "test_transfer_two_to_three_segments_is_exact_for_the_exact_map",
        "test_export_round_trip",
    ),
    "test_control.py": (
        "test_batched_step_matches_single_steps",
        "test_saturate_clips_bend_length_and_twist",
        "test_scaled_dls_step_solves_the_task_and_respects_the_step_limit",
        "test_scaled_dls_step_adds_the_secondary_step_in_the_null_space",
    ),
    "test_cosserat_cc.py": ("test_one_segment_is_the_cc_arc_at_every_station",),
    "test_cosserat_solver.py": (
        "test_newton_residual_reaches_1e_10_and_rounding_level",
        "test_textbook_cantilevers_in_the_linear_range",
        "test_batched_equals_per_sample",
        "test_chunks_in_threads_equal_one_serial_solve",
    ),
    "test_cosserat_spec.py": ("test_routing_geometry_and_refused_robots",),
    "test_data.py": (
        "test_samples_respect_limits_and_are_uniform_in_area_over_the_bending_disk",
        "test_clean_samples_are_consistent_with_encoder_and_kinematics",
    ),
    "test_examples_track_port.py": ("test_capsules_join_consecutive_points_and_skip_coincident_ones",),
    "test_export.py": (
        "test_exported_fk_and_jacobian_equal_lightning",
        "test_exported_ik_equals_lightning_and_satisfies_constraint",
        "test_loaded_module_handles_batch_dims_and_dtype",
        "test_aoti_package_equals_lightning",
        "test_aoti_jacobian_package_equals_lightning",
        "test_exported_float32_jacobian_matches_jacrev",
        "test_metadata_records_spec_units_and_checkpoint",
    ),
    "test_hardware_ccmodel.py": (
        "test_axial_marker_is_the_previous_model",
        "test_lateral_marker_is_the_tip_pose_applied_to_the_marker",
        "test_common_joint_rotation_turns_the_whole_tip_and_the_lateral_marker",
        "test_strain_is_a_path_length_proportional_shift_of_the_commands",
        "test_zero_strain_is_the_model_without_it",
        "test_pure_strain_stretches_each_tendon_in_proportion_to_its_length",
    ),
    "test_hardware_compositional_model.py": (
        "test_untrained_model_is_the_calibrated_cc_model",
        "test_composition_matches_an_independent_product_of_exponentials",
        "test_without_torsion_the_corrections_do_not_roll_about_the_segment_axis",
        "test_history_variant_feeds_each_segment_its_own_memory",
    ),
    "test_hardware_cosserat.py": ("test_the_weight_is_a_free_direction_with_a_non_negative_magnitude",),
    "test_hardware_deploy_checkpoint.py": (
        "test_model_inputs_of_servo_commands_need_no_recording",
        "test_the_cc_model_saves_as_a_zero_residual_member",
        "test_round_trip_is_weights_only_and_predicts_the_same",
    ),
    "test_hardware_deploy_compositional_inference.py": (
        "test_an_untrained_model_is_the_calibrated_cc_model",
        "test_inference_module_equals_predict",
        "test_jacobian_matches_autograd_in_float64",
    ),
    "test_hardware_deploy_export.py": (
        "test_export_of_a_hardware_checkpoint_equals_the_model",
        "test_export_equals_the_eager_model",
    ),
    "test_hardware_deploy_generated.py": (
        "test_generated_fk_equals_predict",
        "test_generated_fk_equals_predict_of_the_compositional_model",
        "test_generated_fk_computes_every_sigma_term_like_predict",
        "test_the_exported_generated_program_equals_the_eager_model",
    ),
    "test_hardware_deploy_inference.py": (
        "test_segment_pose_from_twist_is_cc_transform",
        "test_segment_pose_gradient_is_finite_and_right_at_zero_bending",
        "test_tip_jacobian_in_closed_form_is_autograds_of_the_cc_chain",
        "test_inference_module_equals_the_library_model_run_causally",
        "test_jacobian_matches_autograd_in_float64",
        "test_inference_module_includes_the_lateral_marker",
        "test_inference_module_includes_the_strain",
        "test_the_exported_fk_computes_the_stored_sigma_model_like_predict",
    ),
    "test_hardware_deploy_uncertainty.py": (
        "test_ensemble_only_model_is_the_sigma_calibration",
        "test_spearman_matches_scipy",
        "test_support_score_is_larger_outside_the_training_box",
    ),
    "test_hardware_metrics.py": ("test_offset_removed_rmse_hand_computed",),
    "test_hardware_slack.py": (
        "test_slack_encoder_balances_forces_so_straight_tendons_cause_no_torsion",
        "test_enumerated_qp_is_the_iterative_solution_and_optimal",
        "test_enumerated_qp_in_float32_is_the_float64_solution_to_float32_rounding",
    ),
    "test_hardware_study_benchmark.py": ("test_fit_hardware_model_trains_a_compositional_ensemble",),
    "test_hardware_study_heldout.py": (
        "test_sigma_models_fit_on_held_out_folds_of_a_labelled_recording",
        "test_the_sigma_models_held_out_rows_are_the_selection_proxies_own_fits",
    ),
    "test_hardware_study_selection.py": ("test_bootstrap_weights_and_rmse_equal_the_resampled_rows",),
    "test_ik.py": (
        "test_limits_projection_is_the_nearest_admissible_point",
        "test_unrolled_spd_solve_equals_torch",
    ),
    "test_ik_deploy.py": ("test_exported_refinement_equals_the_eager_one",),
    "test_ik_models.py": ("test_learned_fk_jacobian_equals_autodiff",),
    "test_inference.py": (
        "test_folded_fk_and_ik_equal_models_float64",
        "test_jacobian_module_equals_jacrev",
    ),
    "test_inference_compositional.py": (
        "test_folded_equals_model_float64",
        "test_jacobian_module_equals_jacrev_float64",
    ),
    "test_kinematics.py": (
        "test_forward_kinematics_matches_classic_arc",
        "test_single_segment_near_straight_matches_classic_arc",
        "test_rotation_is_proper_orthonormal",
        "test_bending_coefficients_match_closed_form_both_branches",
        "test_single_segment_matches_pytorch_kinematics_chain",
        "test_multi_segment_matches_pytorch_kinematics_chain",
        "test_backbone_points_on_the_arcs",
        "test_analytic_ik_inverts_fk",
        "test_analytic_ik_exactly_straight_is_finite",
        "test_gradient_at_straight_is_finite_and_correct",
        "test_batched_equals_per_sample_loop",
        "test_float32_follows_input_and_is_accurate",
        "test_torch_export_matches_eager_and_does_not_poison_eager_calls",
        "test_cc_pose_and_jacobian_is_reverse_mode_autodiff",
    ),
    "test_layers.py": (
        "test_decoder_matches_geometric_reference",
        "test_round_trip_every_type_routing_layout",
        "test_encoder_is_least_squares_projection",
        "test_common_mode_offsets_vanish_symmetric_type0",
        "test_batched_equals_per_sample_loop",
        "test_float32_follows_input_and_is_accurate",
        "test_module_to_dtype",
    ),
    "test_legacy_checkpoints.py": (
        "test_checkpoint_of_main_loads_and_predicts_as_it_did",
        "test_hardware_model_of_main_loads_and_predicts_as_it_did",
    ),
    "test_lie.py": (
        "test_twist_exp_tangent_is_autograds_directional_derivative",
        "test_coefficient_derivatives_are_autograds_on_both_branches",
        "test_twist_exp_equals_matrix_exp",
        "test_twist_exp_of_cc_twist_is_the_cc_arc",
        "test_twist_exp_tangent_matches_forward_mode_autodiff",
        "test_twist_exp_and_tangents_are_forward_mode_autodiff",
        "test_roll_z_and_tangents_are_forward_mode_autodiff",
        "test_chain_jacobian_is_reverse_mode_autodiff_of_the_product",
        "test_chain_jacobian_with_a_fixed_base_and_point_is_reverse_mode_autodiff",
        "test_twist_chain_jacobian_is_the_composition_of_the_tensor_wrappers",
    ),
    "test_models.py": (
        "test_front_end_and_fk_batched_equal_single_in_float32",
        "test_clarke_front_end_selects_exactly_the_actuated_columns",
        "test_clarke_ik_outputs_satisfy_the_displacement_constraint",
        "test_quaternion_head_and_bad_options",
    ),
    "test_robot.py": ("test_defaults_and_explicit_layout",),
    "test_sampler.py": ("test_squash_maps_everything_inside_the_limits_and_inverts",),
    "test_training.py": (
        "test_decoded_features_are_those_of_the_decoded_joints",
        "test_pose_loss_vanishes_at_the_true_joints",
        "test_training_loss_combines_feature_and_pose_terms",
        "test_limit_noise_adds_the_penalty_at_noisy_inputs",
        "test_input_pose_inverts_the_standardised_input_and_maps_any_vector_to_a_pose",
        "test_pose_noise_adds_the_pose_loss_at_perturbed_training_poses",
        "test_limit_excess_is_zero_inside_the_limits_and_the_relative_overshoot_squared_outside",
        "test_limit_weight_adds_the_mean_limit_excess_of_the_decoded_features",
    ),
}

# Modules whose second pass runs in the slow tests' process (balance; test_ik_deploy.py's export is a slow test, so
# its second pass, which runs that export, belongs here). Quiet `make test` of ba2ae56, without test_cosserat_solver.py
# here: the slow tests 9 min 3 s and their second pass 11 s, the rest 8 min 6 s and its second pass 1 min 31 s. Since
# then about 110 s were cut from the slow tests and two of the rest's tests over 20 s (48 s) marked slow: that
# module's second pass, about 15 s, runs here again.
BESIDE_THE_SLOW_TESTS: frozenset[str] = frozenset({"test_cosserat_solver.py", "test_hardware_cosserat.py",
                                                   "test_ik_deploy.py"})


if __name__ == "__main__":       # `python tests/reduction_order.py beside|rest`: the files of make test's second passes
    import sys

    beside = {"beside": True, "rest": False}[sys.argv[1]]
    print(" ".join(f"tests/{m}" for m in sorted(REDUCTION_ORDER) if (m in BESIDE_THE_SLOW_TESTS) == beside))
