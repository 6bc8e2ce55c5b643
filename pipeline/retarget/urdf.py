"""A URDF written from a compiled MuJoCo model, for placo (which reads URDF only, not MJCF).

Links are the model's bodies (inertia kept, no geometry: placo's IK needs none), hinge joints
become revolute joints with their ranges, bodies without a joint become fixed joints, and every
site becomes a fixed child link of its body, so the `track_<name>` frames exist in placo too.
The root body's free joint is left out: placo adds the floating base itself.
"""

from __future__ import annotations

import mujoco
import numpy as np

from pipeline.common import quat


def _rpy(q: np.ndarray) -> str:
    m = quat.to_matrix(np.asarray(q, float))
    # URDF rpy: R = Rz(yaw) Ry(pitch) Rx(roll).
    pitch = np.arcsin(-np.clip(m[2, 0], -1.0, 1.0))
    roll = np.arctan2(m[2, 1], m[2, 2])
    yaw = np.arctan2(m[1, 0], m[0, 0])
    return f"{roll:.9g} {pitch:.9g} {yaw:.9g}"


def _xyz(v) -> str:
    return " ".join(f"{x:.9g}" for x in v)


def mjcf_to_urdf(model: mujoco.MjModel, name: str = "g1") -> str:
    out = ['<?xml version="1.0"?>', f'<robot name="{name}">']
    for b in range(1, model.nbody):
        body = model.body(b).name
        inertia = model.body_inertia[b]
        out.append(
            f'<link name="{body}"><inertial><origin xyz="{_xyz(model.body_ipos[b])}" rpy="{_rpy(model.body_iquat[b])}"/>'
            f'<mass value="{max(model.body_mass[b], 1e-6):.9g}"/>'
            f'<inertia ixx="{inertia[0]:.9g}" ixy="0" ixz="0" iyy="{inertia[1]:.9g}" iyz="0" izz="{inertia[2]:.9g}"/>'
            f"</inertial></link>"
        )
        parent = model.body_parentid[b]
        if parent == 0:
            continue  # the floating root
        joints = [j for j in range(model.njnt) if model.jnt_bodyid[j] == b]
        origin = f'<origin xyz="{_xyz(model.body_pos[b])}" rpy="{_rpy(model.body_quat[b])}"/>'
        head = f'<parent link="{model.body(parent).name}"/><child link="{body}"/>'
        if joints and model.jnt_type[joints[0]] == mujoco.mjtJoint.mjJNT_HINGE:
            j = joints[0]
            lo, hi = model.jnt_range[j]
            out.append(
                f'<joint name="{model.joint(j).name}" type="revolute">{origin}{head}'
                f'<axis xyz="{_xyz(model.jnt_axis[j])}"/>'
                f'<limit lower="{lo:.9g}" upper="{hi:.9g}" effort="1000" velocity="100"/></joint>'
            )
        else:
            out.append(f'<joint name="{body}_fixed" type="fixed">{origin}{head}</joint>')
    for s in range(model.nsite):
        site, body = model.site(s).name, model.body(model.site_bodyid[s]).name
        out.append(f'<link name="{site}"/>')
        out.append(
            f'<joint name="{site}_fixed" type="fixed"><origin xyz="{_xyz(model.site_pos[s])}" rpy="{_rpy(model.site_quat[s])}"/>'
            f'<parent link="{body}"/><child link="{site}"/></joint>'
        )
    out.append("</robot>")
    return "\n".join(out)
