"""MJCF models for the MuJoCo driver and the kinematic controllers: loading and name lookups.

Config checks load a model once to name what is missing (a joint, a site, a sensor) before
anything starts; the driver and controllers load their own copies to simulate or compute.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import mujoco
import numpy as np

from .files import check_regular
from .logutil import RateLimitedLogger

log = logging.getLogger(__name__)
_warnings = RateLimitedLogger(log)


def _mujoco_warning(text: str) -> None:
    """MuJoCo's warnings (an unstable simulation, a full contact buffer) into the log, rate
    limited per kind: by default MuJoCo appends them to MUJOCO_LOG.TXT in the current folder."""
    _warnings.warning(text.split(" at ")[0].split(". ")[0], "MuJoCo: %s", text.strip())


def load_model(path: str | Path) -> mujoco.MjModel:
    """The model at ``path``; MuJoCo reads the file itself, so it is checked to be a regular
    file first (a FIFO would hang MuJoCo's read, a device fill memory)."""
    check_regular(path)
    mujoco.set_mju_user_warning(_mujoco_warning)
    return mujoco.MjModel.from_xml_path(str(path))


@dataclass(frozen=True)
class ModelNames:
    """The names a config may refer to, with what each sensor measures."""

    joints: frozenset[str]
    sites: frozenset[str]
    sensors: dict[str, int]  # name -> dimension
    actuated_joints: frozenset[str]


@lru_cache(maxsize=16)
def model_names(path: str) -> ModelNames:
    """Names in the model at ``path``; raises ValueError with MuJoCo's message if it does not load."""
    try:
        model = load_model(path)
    except Exception as exc:  # MuJoCo raises ValueError with the parser's message
        raise ValueError(f"cannot load the model {path}: {exc}") from None

    def names(kind: mujoco.mjtObj, count: int) -> list[str]:
        return [mujoco.mj_id2name(model, kind, i) or "" for i in range(count)]

    joints = names(mujoco.mjtObj.mjOBJ_JOINT, model.njnt)
    actuated = {
        joints[model.actuator_trnid[i, 0]]
        for i in range(model.nu)
        if int(model.actuator_trntype[i]) == int(mujoco.mjtTrn.mjTRN_JOINT)
    }
    sensor_names = names(mujoco.mjtObj.mjOBJ_SENSOR, model.nsensor)
    return ModelNames(
        joints=frozenset(joints),
        sites=frozenset(names(mujoco.mjtObj.mjOBJ_SITE, model.nsite)),
        sensors={n: int(model.sensor_dim[i]) for i, n in enumerate(sensor_names)},
        actuated_joints=frozenset(actuated),
    )


def joint_addresses(model: mujoco.MjModel, names: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """qpos and dof addresses of 1-DOF joints (hinge or slide), in the order of ``names``."""
    qpos, dof = [], []
    for name in names:
        jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if jid < 0:
            raise KeyError(f'joint "{name}" is not in the model')
        if int(model.jnt_type[jid]) not in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)):
            raise ValueError(f'joint "{name}" is not a hinge or slide joint')
        qpos.append(model.jnt_qposadr[jid])
        dof.append(model.jnt_dofadr[jid])
    return np.array(qpos, dtype=np.intp), np.array(dof, dtype=np.intp)


def actuator_for_joints(model: mujoco.MjModel, names: list[str]) -> np.ndarray:
    """The id of the actuator driving each joint directly (-1 where none)."""
    by_joint: dict[int, int] = {}
    for i in range(model.nu):
        if int(model.actuator_trntype[i]) == int(mujoco.mjtTrn.mjTRN_JOINT):
            by_joint.setdefault(int(model.actuator_trnid[i, 0]), i)
    ids = []
    for name in names:
        jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        ids.append(by_joint.get(jid, -1))
    return np.array(ids, dtype=np.intp)


def sensor_slice(model: mujoco.MjModel, name: str) -> slice:
    sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, name)
    if sid < 0:
        raise KeyError(f'sensor "{name}" is not in the model')
    adr = int(model.sensor_adr[sid])
    return slice(adr, adr + int(model.sensor_dim[sid]))
