"""Log Lift episodes (recorded or rolled out) to rerun on LeRobot's timelines.

One `EpisodeLogger.log_step` call per frame: camera image, state, the 8-D action (also as an arrow at
the end effector in 3D), gripper, reward, success, and for rollouts the policy's predicted action,
value estimate and theta_t. Used by `bcrl-viz` (datasets) and by rollouts (bcrl-finetune, lerobot-eval).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lerobot_bcrl import features as F
from lerobot_bcrl.geometry import ACTION_NAMES

# Deltas are a few millimetres per step: draw the arrows this many times longer so they can be seen.
ARROW_SCALE = 10.0


class EpisodeLogger:
    """Writes one rerun recording; `save_path` makes it a .rrd file instead of a live viewer."""

    def __init__(self, application_id: str, save_path: Path | None = None, spawn: bool = False, fps: int = 20):
        import rerun as rr
        import rerun.blueprint as rrb

        self.rr = rr
        self.fps = fps
        self.stream = rr.RecordingStream(application_id)
        blueprint = rrb.Blueprint(
            rrb.Horizontal(
                rrb.Vertical(rrb.Spatial2DView(origin="camera"), rrb.Spatial3DView(origin="world")),
                rrb.Vertical(
                    rrb.TimeSeriesView(origin="action"),
                    rrb.TimeSeriesView(origin="state"),
                    rrb.TimeSeriesView(origin="signals"),
                ),
            )
        )
        if save_path is not None:
            Path(save_path).parent.mkdir(parents=True, exist_ok=True)
            self.stream.save(save_path, default_blueprint=blueprint)
        elif spawn:
            self.stream.spawn(default_blueprint=blueprint)
        self.stream.log("action", rr.SeriesLines(names=ACTION_NAMES), static=True)
        self._eef_path: list[np.ndarray] = []
        self._grasp_logged = False

    def log_policy_outputs(self, frame_index: int, predicted_action, value) -> None:
        """What the policy predicted for this frame (beside what the env then did)."""
        self.log_step(frame_index, {"policy.action": predicted_action, "policy.value": value})

    def set_time(self, frame_index: int) -> None:
        self.stream.set_time("frame_index", sequence=frame_index)
        self.stream.set_time("timestamp", duration=frame_index / self.fps)

    def log_step(self, frame_index: int, frame: dict) -> None:
        """`frame` holds dataset-style keys (any subset): images, state, env state, action, aux, next.*;
        rollouts may add `policy.action`, `policy.value`, `theta_t`."""
        rr, log = self.rr, self.stream.log
        self.set_time(frame_index)
        if F.IMAGE_KEY in frame:
            log(f"camera/{F.CAMERA_NAME}", rr.Image(_hwc_uint8(frame[F.IMAGE_KEY])))
        state = _np(frame.get(F.STATE_KEY))
        action = _np(frame.get(F.ACTION_KEY))
        if state is not None:
            log("state", rr.Scalars(state))
            eef_pos = state[F.STATE_EEF_POS]
            self._eef_path.append(eef_pos)
            log("world/eef", rr.Points3D([eef_pos], radii=0.008, colors=[[40, 120, 255]]))
            log("world/eef_path", rr.LineStrips3D([np.stack(self._eef_path)], colors=[[40, 120, 255]]))
            if action is not None:
                log("world/action/delta_pos", rr.Arrows3D(origins=[eef_pos], vectors=[action[:3] * ARROW_SCALE], colors=[[255, 160, 0]]))
        env_state = _np(frame.get(F.ENV_STATE_KEY))
        if env_state is not None:
            log("world/cube", rr.Points3D([env_state[:3]], radii=0.02, colors=[[220, 30, 30]]))
        if action is not None:
            log("action", rr.Scalars(action))
            log("signals/gripper", rr.Scalars(action[7:8]))
        grasp_valid = _np(frame.get(F.AUX_GRASP_VALID_KEY))
        grasp = _np(frame.get(F.AUX_GRASP_POS_KEY))
        if grasp is not None and not self._grasp_logged and (grasp_valid is None or bool(grasp_valid.reshape(-1)[0])):
            # one grasp location per episode: a static point
            log("world/grasp", rr.Points3D([grasp], radii=0.012, colors=[[255, 0, 255]]), static=True)
            self._grasp_logged = True
        for key, entity in (
            (F.REWARD_KEY, "signals/reward"),
            (F.SUCCESS_KEY, "signals/success"),
            (F.DONE_KEY, "signals/done"),
            ("policy.value", "signals/value"),
            ("theta_t", "signals/theta_t"),
        ):
            value = _np(frame.get(key))
            if value is not None:
                log(entity, rr.Scalars(value.astype(np.float64).reshape(-1)[:1]))
        predicted = _np(frame.get("policy.action"))
        if predicted is not None:
            log("policy/action", rr.Scalars(predicted))
            if self._eef_path:  # this frame's EEF, or the last one logged (predictions come before the step)
                log("world/policy/delta_pos", rr.Arrows3D(origins=[self._eef_path[-1]], vectors=[predicted[:3] * ARROW_SCALE], colors=[[0, 200, 120]]))

    def close(self) -> None:
        self.stream.flush()
        self.stream.disconnect()


def _np(value) -> np.ndarray | None:
    if value is None:
        return None
    if hasattr(value, "detach"):
        value = value.detach().cpu().numpy()
    return np.asarray(value)


def _hwc_uint8(image) -> np.ndarray:
    """Dataset images come as float CHW in [0, 1], env images as uint8 HWC."""
    image = _np(image)
    if image.dtype != np.uint8:
        image = (np.clip(image, 0, 1) * 255).round().astype(np.uint8)
    if image.shape[0] in (1, 3) and image.shape[-1] not in (1, 3):
        image = np.transpose(image, (1, 2, 0))
    return image


def read_entity_rows(rrd_path: Path) -> dict[str, int]:
    """Rows logged per entity path in an .rrd file (static rows included), read with rerun's own API."""
    from rerun.experimental import RrdReader

    rows: dict[str, int] = {}
    for chunk in RrdReader(str(rrd_path)).store().stream().to_chunks():
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    return rows


# Rollout loggers of the envs in this process, by position in the vector env (SyncVectorEnv creates its
# envs in order), so a policy running in the same process can log its predictions beside what happened.
_ROLLOUT_SLOTS: list["RolloutSlot"] = []


class RolloutSlot:
    """One env's place in this process; holds the logger of its current episode and its step count."""

    def __init__(self):
        self.logger: EpisodeLogger | None = None
        self.frame_index = 0
        _ROLLOUT_SLOTS.append(self)

    @property
    def position(self) -> int:
        """Index in this process's envs, i.e. in the policy's batch."""
        return _ROLLOUT_SLOTS.index(self)

    def close_episode(self) -> None:
        if self.logger is not None:
            self.logger.close()
            self.logger = None

    def release(self) -> None:
        self.close_episode()
        if self in _ROLLOUT_SLOTS:
            _ROLLOUT_SLOTS.remove(self)


def log_policy_step(actions, values) -> None:
    """Called by the policy with its batch of predictions; a no-op unless envs here log to rerun."""
    if not _ROLLOUT_SLOTS:
        return
    actions, values = _np(actions), _np(values)
    if values is None:  # a privileged critic without its input (the policy acting alone) gives no value
        values = [None] * len(actions)
    for slot, action, value in zip(_ROLLOUT_SLOTS, actions, values):
        if slot.logger is not None:
            slot.logger.log_policy_outputs(slot.frame_index, action, value)


def annotate_rollouts(values: dict[str, float]) -> None:
    """Log run-level numbers (theta_t, env steps) at the current frame of every active rollout logger."""
    for slot in _ROLLOUT_SLOTS:
        if slot.logger is not None and values:
            slot.logger.set_time(slot.frame_index)
            for name, value in values.items():
                slot.logger.stream.log(f"signals/{name}", slot.logger.rr.Scalars([float(value)]))
