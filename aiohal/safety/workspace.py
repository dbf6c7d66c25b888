"""Workspace limits: sites of the robot's model kept inside a box or a sphere (R-HAL's limits
for working beside people).

Every tick the measured joint positions go through the model's forward kinematics
(``mj_kinematics``) and each configured site is placed in its frame; a site outside its
shape (or a position that is not finite) is a violation, with its distance outside. Built
only when ``[[safety.workspace]]`` is configured: without it nothing of this runs in the tick.
The model's joints that the robot does not have stay at the model's reference pose (a
floating base, for instance, where the model puts it).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .levels import SafetyLevel, WorkspaceSection


class WorkspaceMonitor:
    def __init__(
        self, model_path: str | Path, joint_names: list[str], position: np.ndarray, entries: list[WorkspaceSection]
    ) -> None:
        import mujoco  # the `sim` extra: loaded only for a configured workspace

        from .. import mjcf

        self._mujoco = mujoco
        self.model = model = mjcf.load_model(model_path)
        self.data = mujoco.MjData(model)
        names = mjcf.model_names(str(model_path))
        mine = [i for i, name in enumerate(joint_names) if name in names.joints]
        self._rows = np.array(mine, dtype=np.intp)
        self._qadr, _ = mjcf.joint_addresses(model, [joint_names[i] for i in mine])
        self._q = np.empty(len(mine))
        self._position = position
        self.entries = entries
        self.levels = [SafetyLevel[e.level.upper()] for e in entries]
        self._sites, self._frames = [], []
        for e in entries:
            self._sites.append(mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, e.site))
            self._frames.append(
                0 if e.frame == "world" else mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, e.frame)
            )
        self._local = np.empty(3)
        self.outside = -1  # the entry a site is outside of, -1: all inside
        self.distance = 0.0  # how far outside (m)
        self.where = np.zeros(3)  # the site's position in its frame

    @staticmethod
    def name_issues(model_path: str | Path, entries: list[WorkspaceSection]) -> list[tuple[str, str]]:
        """(key, message) for sites and frames the model does not have."""
        import mujoco

        from .. import mjcf

        model = mjcf.load_model(model_path)
        issues = []
        for i, e in enumerate(entries):
            if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, e.site) < 0:
                issues.append((f"safety.workspace[{i}].site", f'no site "{e.site}" in the model'))
            if e.frame != "world" and mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, e.frame) < 0:
                issues.append((f"safety.workspace[{i}].frame", f'no body "{e.frame}" in the model'))
        return issues

    def check(self) -> bool:
        """Place every site from the measured positions; False (and ``outside``, ``distance``,
        ``where`` set) when one is outside its shape."""
        np.take(self._position, self._rows, out=self._q)
        data = self.data
        data.qpos[self._qadr] = self._q
        self._mujoco.mj_kinematics(self.model, data)
        local = self._local
        for i, e in enumerate(self.entries):
            np.copyto(local, data.site_xpos[self._sites[i]])
            body = self._frames[i]
            if body:
                local -= data.xpos[body]
                local[:] = data.xmat[body].reshape(3, 3).T @ local
            x, y, z = local
            if e.box is not None:
                (x0, y0, z0), (x1, y1, z1) = e.box.min, e.box.max
                dx, dy, dz = max(x0 - x, 0.0, x - x1), max(y0 - y, 0.0, y - y1), max(z0 - z, 0.0, z - z1)
                distance = math.sqrt(dx * dx + dy * dy + dz * dz)
            else:
                # an entry has a box or a sphere (the config's check); no test added to the tick
                cx, cy, cz = e.sphere.center  # type: ignore[union-attr]
                distance = math.sqrt((x - cx) ** 2 + (y - cy) ** 2 + (z - cz) ** 2) - e.sphere.radius  # type: ignore[union-attr]
            if not distance <= 0.0:  # outside, or not finite
                self.outside, self.distance = i, distance
                np.copyto(self.where, local)
                return False
        self.outside = -1
        return True
