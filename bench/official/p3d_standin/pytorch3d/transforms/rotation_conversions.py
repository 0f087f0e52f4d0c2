"""Stand-in for the few `pytorch3d.transforms.rotation_conversions` functions the official
PM-Avatars code imports, so it runs without pytorch3d. Written for this harness from the
usual formulas (Rodrigues, unit quaternions); only speed is measured with it, so agreement
with pytorch3d to float rounding is enough.
"""

import torch


def axis_angle_to_quaternion(axis_angle):
    """(w, x, y, z), real part first."""
    angle = torch.linalg.norm(axis_angle, dim=-1, keepdim=True)
    half = 0.5 * angle
    # sin(h)/angle·v with the small-angle limit 1/2 so tiny rotations stay exact.
    small = angle.abs() < 1e-6
    k = torch.where(small, 0.5 - angle * angle / 48.0,
                    torch.sin(half) / torch.where(small, torch.ones_like(angle), angle))
    return torch.cat([torch.cos(half), axis_angle * k], dim=-1)


def quaternion_to_matrix(q):
    w, x, y, z = torch.unbind(q, -1)
    two_s = 2.0 / (q * q).sum(-1)
    m = torch.stack(
        (
            1 - two_s * (y * y + z * z), two_s * (x * y - z * w), two_s * (x * z + y * w),
            two_s * (x * y + z * w), 1 - two_s * (x * x + z * z), two_s * (y * z - x * w),
            two_s * (x * z - y * w), two_s * (y * z + x * w), 1 - two_s * (x * x + y * y),
        ),
        -1,
    )
    return m.reshape(q.shape[:-1] + (3, 3))


def axis_angle_to_matrix(axis_angle):
    return quaternion_to_matrix(axis_angle_to_quaternion(axis_angle))


def matrix_to_quaternion(m):
    """Shepperd's method: the largest of the four diagonal combinations picks the branch."""
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    cands = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22,
                         1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    best = cands.argmax(-1)
    r = torch.sqrt(cands.clamp(min=1e-12))
    rows = [
        torch.stack([r[..., 0] ** 2, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1) / (2 * r[..., 0:1]),
        torch.stack([m[..., 2, 1] - m[..., 1, 2], r[..., 1] ** 2, m[..., 1, 0] + m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0]], -1) / (2 * r[..., 1:2]),
        torch.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] + m[..., 0, 1], r[..., 2] ** 2, m[..., 2, 1] + m[..., 1, 2]], -1) / (2 * r[..., 2:3]),
        torch.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 2, 1] + m[..., 1, 2], r[..., 3] ** 2], -1) / (2 * r[..., 3:4]),
    ]
    q = torch.stack(rows, -2)
    q = torch.gather(q, -2, best[..., None, None].expand(best.shape + (1, 4))).squeeze(-2)
    return torch.where(q[..., :1] < 0, -q, q)


def quaternion_to_axis_angle(q):
    norm = torch.linalg.norm(q[..., 1:], dim=-1, keepdim=True)
    half = torch.atan2(norm, q[..., :1])
    angle = 2 * half
    small = angle.abs() < 1e-6
    k = torch.where(small, 0.5 - angle * angle / 48.0,
                    torch.sin(half) / torch.where(small, torch.ones_like(angle), angle))
    return q[..., 1:] / k


def matrix_to_axis_angle(m):
    return quaternion_to_axis_angle(matrix_to_quaternion(m))
