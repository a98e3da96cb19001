"""RepNet training: train, export (ONNX) and evaluate the 2D-to-3D lifter on Human3.6M.

Wandt & Rosenhahn 2019, "RepNet: Weakly Supervised Training of an Adversarial Reprojection
Network for 3D Human Pose Estimation", CVPR. Each equation of the paper (the seed's numbering),
the code that implements it, and the test (in tests.training) that checks it:

Eq. 1  W' = K X: the reprojection layer, weak perspective
    code: repnet.train.camera.project_weak_perspective
    test: test_camera.test_projection_is_k_times_x_for_every_joint
Eq. 2  L_rep = ||W - K X||_F: the reprojection loss (hidden joints' columns zeroed)
    code: repnet.train.losses.reprojection_loss
    test: test_losses.test_reprojection_loss_is_zero_for_exact_projection_with_any_translation
    test: test_losses.test_reprojection_loss_ignores_missing_joints
Eq. 3  b = p_child - p_parent: a bone vector
    code: repnet.train.losses.bone_lengths
    code: repnet.core.skeleton.bone_matrix
    test: test_skeleton.test_each_bone_matrix_column_is_a_bone_vector_child_minus_parent
    test: test_losses.test_bone_loss_is_zero_at_the_mean_skeleton_and_grows_with_a_stretched_limb
Eq. 4  c: the vector that defines a bone, +1 at its child and -1 at its parent, b = X c
    code: repnet.core.skeleton.bone_matrix
    test: test_skeleton.test_each_bone_matrix_column_is_a_bone_vector_child_minus_parent
Eq. 5-6  B = (b_1, ..., b_B) = X C: all bone vectors of a pose
    code: repnet.core.skeleton.bone_matrix
    code: repnet.train.model.KCS
    test: test_skeleton.test_each_bone_matrix_column_is_a_bone_vector_child_minus_parent
Eq. 7  Psi = B^T B: the kinematic chain space (KCS) matrix the critic sees
    code: repnet.train.model.KCS
    test: test_model.test_kcs_is_the_gram_matrix_of_the_bone_vectors
    test: test_model.test_kcs_diagonal_holds_squared_bone_lengths
Eq. 8  K K^T = s^2 I: K is a scaled orthographic projection
    code: repnet.train.losses.camera_loss
    code: repnet.core.geometry.rotation_of_camera
    test: test_camera.test_a_scaled_rotation_has_scale_s_and_k_kt_equal_to_s_squared_i
    test: test_losses.test_camera_loss_is_zero_for_scaled_orthographic_camera
Eq. 9  s = sqrt(trace(K K^T) / 2): the scale in K
    code: repnet.train.camera.camera_scale
    test: test_camera.test_a_scaled_rotation_has_scale_s_and_k_kt_equal_to_s_squared_i
Eq. 10  L_cam = ||2 / trace(K K^T) K K^T - I_2||_F: the camera loss
    code: repnet.train.losses.camera_loss
    test: test_losses.test_camera_loss_is_zero_for_scaled_orthographic_camera
    test: test_losses.test_camera_loss_is_positive_for_skewed_camera
Sec. 4.3  the symmetry error: sum over the arm and leg bones of |left - right| length
    code: repnet.train.metrics.symmetry_error
    code: repnet.core.skeleton.SYMMETRIC_BONES
    test: test_metrics.test_symmetry_error_sums_left_right_bone_differences

Not numbered in the paper: the critic's WGAN-GP loss (Gulrajani et al. 2017) is
repnet.train.losses.critic_loss and repnet.train.losses.gradient_penalty. Code cites the paper as
"Wandt & Rosenhahn 2019, Eq. n"; tests/training/test_paper_map.py checks this map, and that each
citation in training/ stands in a function or class the map names for that equation.

Symbols, here and in every docstring and shape comment: N poses (a batch), J = 17 joints, B = 16
bones, K the (N, 2, 3) weak-perspective camera, W the normalised 2D input, X the 3D pose; D = 16
the joints of a Stacked-Hourglass (MPII) detection. `visible` (N, J) in {0, 1} is the visibility
mask: the ONNX input `visibility` thresholded at 0.5 (model.LiftingGraph); a joint with
visibility 0 is hidden.
"""

# This folder is the source of `repnet.train`, the only name an install gives it (pyproject.toml's
# package-dir). Python run from the checkout's root would also find it under the folder's own name,
# a second copy of every module beside the installed one: refused, with the name to use.
if __name__ != "repnet.train":
    raise ImportError(
        f"{__name__!r} is the source folder of the package repnet.train: import repnet.train "
        "(pip install -e .)"
    )


# onnxruntime's usage telemetry off before training, export, evaluation or adapt makes a session of
# its own (issue 31): the service's session module turns it off when it is imported.
import repnet.runtime.session  # noqa: E402, F401
