import numpy as np
import torch
from scipy.spatial.transform import Rotation

from voxfusion.core.lie import perturb_right, se3_exp, so3_exp


def test_so3_matches_scipy_and_small_angles():
    phi = torch.tensor([[0.3, -0.2, 0.9], [1e-9, 0.0, 0.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
    np.testing.assert_allclose(so3_exp(phi).numpy(), Rotation.from_rotvec(phi.numpy()).as_matrix(), atol=1e-12)


def test_se3_is_rigid_and_identity_at_zero_and_matches_matrix_exponential():
    xi = torch.tensor([0.1, -0.3, 0.2, 0.4, -0.1, 0.25], dtype=torch.float64)
    T = se3_exp(xi)
    R = T[:3, :3]
    np.testing.assert_allclose((R @ R.T).numpy(), np.eye(3), atol=1e-12)
    np.testing.assert_allclose(se3_exp(torch.zeros(6, dtype=torch.float64)).numpy(), np.eye(4))
    hat = torch.zeros(4, 4, dtype=torch.float64)
    hat[:3, :3] = torch.tensor([[0, -xi[5], xi[4]], [xi[5], 0, -xi[3]], [-xi[4], xi[3], 0]])
    hat[:3, 3] = xi[:3]
    np.testing.assert_allclose(T.numpy(), torch.linalg.matrix_exp(hat).numpy(), atol=1e-12)


def test_right_perturbation_moves_along_camera_axes_and_has_gradients():
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = torch.as_tensor(Rotation.from_euler("z", 90, degrees=True).as_matrix())
    xi = torch.tensor([0.0, 0.0, 0.5, 0.0, 0.0, 0.0], dtype=torch.float64, requires_grad=True)
    T2 = perturb_right(T, xi)
    # camera z axis of T is world z: moving 0.5 along camera z moves the centre 0.5 along world z
    np.testing.assert_allclose(T2[:3, 3].detach().numpy(), [0, 0, 0.5], atol=1e-12)
    T2[:3, 3].sum().backward()
    assert xi.grad is not None and torch.isfinite(xi.grad).all()
    assert torch.autograd.gradcheck(lambda x: se3_exp(x), (torch.rand(6, dtype=torch.float64, requires_grad=True),))


def test_se3_log_inverts_exp_and_matches_scipy():
    """The closed-form log against ``exp`` (round trip) and against scipy's general matrix logarithm,
    from tiny rotations (series branch) to 170 degrees; 180 degrees is refused."""
    import numpy as np
    import pytest
    import scipy.linalg

    from voxfusion.core.lie import se3_exp, se3_log

    g = torch.Generator().manual_seed(0)
    for angle in (0.0, 1e-6, 1e-3, 0.3, 1.5, 2.5, np.deg2rad(170)):
        axis = torch.randn(3, generator=g, dtype=torch.float64)
        xi = torch.cat([torch.randn(3, generator=g, dtype=torch.float64), axis / axis.norm() * angle])
        T = se3_exp(xi)
        torch.testing.assert_close(se3_log(T), xi, rtol=1e-7, atol=1e-9)
        ref = np.real(scipy.linalg.logm(T.numpy()))
        torch.testing.assert_close(se3_log(T), torch.tensor([*ref[:3, 3], ref[2, 1], ref[0, 2], ref[1, 0]]),
                                   rtol=1e-6, atol=1e-8)
    with pytest.raises(ValueError, match="180"):
        se3_log(se3_exp(torch.tensor([0.0, 0, 0, np.pi, 0, 0], dtype=torch.float64)))


def test_numpy_twins_match_the_torch_versions():
    """``se3_exp_np`` / ``se3_log_np`` (host-side pose arithmetic: the motion prior) against ``se3_exp`` /
    ``se3_log``: equal to float64 rounding, any batch shape, the small-angle series included; float32 stays
    float32; the log refuses 180 degrees as the torch one does."""
    import pytest

    from voxfusion.core.lie import se3_exp_np, se3_log, se3_log_np

    g = torch.Generator().manual_seed(1)
    for shape in ((6,), (3, 6), (2, 4, 6)):
        for scale in (0.0, 1e-6, 1e-3, 0.5, 2.0):
            xi = torch.randn(*shape, generator=g, dtype=torch.float64) * scale
            np.testing.assert_allclose(se3_exp_np(xi.numpy()), se3_exp(xi).numpy(), rtol=0, atol=1e-15)
            if xi.dim() == 1:
                T = se3_exp(xi)
                np.testing.assert_allclose(se3_log_np(T.numpy()), se3_log(T).numpy(), rtol=1e-12, atol=1e-15)
    xi32 = (torch.randn(6, generator=g) * 0.1).numpy()
    assert se3_exp_np(xi32).dtype == np.float32
    np.testing.assert_allclose(se3_exp_np(xi32), se3_exp(torch.from_numpy(xi32)).numpy(), rtol=0, atol=1e-6)
    with pytest.raises(ValueError, match="180"):
        se3_log_np(se3_exp_np(np.array([0.0, 0, 0, np.pi, 0, 0])))
