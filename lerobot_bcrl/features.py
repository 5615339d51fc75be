"""Feature names and layouts shared by the env, the datasets and the policy.

Every dataset this project writes (simulated or converted) has these keys; the policy reads them by name.
"""

from __future__ import annotations

from lerobot_bcrl.geometry import ACTION_DIM, ACTION_NAMES

IMAGES_PREFIX = "observation.images."  # LeRobot names a camera <name>'s frames `observation.images.<name>`
CAMERA_NAME = "agentview"
IMAGE_KEY = f"{IMAGES_PREFIX}{CAMERA_NAME}"
STATE_KEY = "observation.state"
ENV_STATE_KEY = "observation.environment_state"
ACTION_KEY = "action"
# Auxiliary labels (method.md section 1). Not `observation.*`: they are targets, never policy inputs.
AUX_EEF_POS_KEY = "aux.eef_pos"
AUX_GRASP_POS_KEY = "aux.grasp_pos"
AUX_GRASP_VALID_KEY = "aux.grasp_valid"
# False on the frames of a planned mistake (bcrl-record --miss_probability: a first grasp missed on purpose,
# then retried): the BC loss skips them, so a policy learns the retry and not the miss.
AUX_IMITATE_KEY = "aux.imitate"
# The delta between consecutive measured EEF poses (same layout as `action`). In simulation `action` is
# what the controller was commanded; robosuite's OSC covers only part of each command, so the two differ.
AUX_PROPRIO_ACTION_KEY = "aux.proprio_action"

REWARD_KEY = "next.reward"
# robosuite's sparse Lift reward per step while the cube is above the table by 4 cm (reward_scale=None); the
# env pays it, the report turns returns back into lifted steps with it.
LIFT_REWARD = 2.25
DONE_KEY = "next.done"
SUCCESS_KEY = "next.success"

STATE_NAMES = (
    ["eef_pos_x", "eef_pos_y", "eef_pos_z", "eef_quat_x", "eef_quat_y", "eef_quat_z", "eef_quat_w"]
    + ["gripper_qpos_0", "gripper_qpos_1"]
    + [f"joint_pos_{i}" for i in range(7)]
)
# The cube's yaw relative to the fingers, d (rad, wrapped to the nearest face: [-pi/4, pi/4)), enters as
# (sin 4d, cos 4d, d / (pi/4)): from the raw quaternions an MLP does not learn the demonstrators' turn to the
# nearest face, and (sin 4d, cos 4d) alone cannot tell +45 from -45 degrees, where that turn flips sign
# (docs/RESULTS.md, "What did not work").
ENV_STATE_NAMES = (
    ["cube_pos_x", "cube_pos_y", "cube_pos_z", "cube_quat_x", "cube_quat_y", "cube_quat_z", "cube_quat_w"]
    + ["eef_to_cube_x", "eef_to_cube_y", "eef_to_cube_z"]
    + ["cube_yaw_to_fingers_sin4", "cube_yaw_to_fingers_cos4", "cube_yaw_to_fingers_turn"]
)
STATE_DIM = len(STATE_NAMES)
ENV_STATE_DIM = len(ENV_STATE_NAMES)
# Slices of observation.state
STATE_EEF_POS = slice(0, 3)
STATE_EEF_QUAT = slice(3, 7)
STATE_GRIPPER_QPOS = slice(7, 9)
# Slices of observation.environment_state
ENV_STATE_CUBE_POS = slice(0, 3)
ENV_STATE_CUBE_QUAT = slice(3, 7)
ENV_STATE_EEF_TO_CUBE = slice(7, 10)  # cube position minus end-effector position (m)


def dataset_features(image_size: int | None, use_videos: bool) -> dict[str, dict]:
    """LeRobotDataset `features` for a Lift dataset; `image_size=None` gives a low-dim dataset."""
    features: dict[str, dict] = {
        STATE_KEY: {"dtype": "float32", "shape": (STATE_DIM,), "names": STATE_NAMES},
        ENV_STATE_KEY: {"dtype": "float32", "shape": (ENV_STATE_DIM,), "names": ENV_STATE_NAMES},
        ACTION_KEY: {"dtype": "float32", "shape": (ACTION_DIM,), "names": ACTION_NAMES},
        AUX_EEF_POS_KEY: {"dtype": "float32", "shape": (3,), "names": ["x", "y", "z"]},
        AUX_GRASP_POS_KEY: {"dtype": "float32", "shape": (3,), "names": ["x", "y", "z"]},
        AUX_GRASP_VALID_KEY: {"dtype": "bool", "shape": (1,), "names": None},
        AUX_IMITATE_KEY: {"dtype": "bool", "shape": (1,), "names": None},
        AUX_PROPRIO_ACTION_KEY: {"dtype": "float32", "shape": (ACTION_DIM,), "names": ACTION_NAMES},
        REWARD_KEY: {"dtype": "float32", "shape": (1,), "names": None},
        DONE_KEY: {"dtype": "bool", "shape": (1,), "names": None},
        SUCCESS_KEY: {"dtype": "bool", "shape": (1,), "names": None},
    }
    if image_size is not None:
        features[IMAGE_KEY] = {
            "dtype": "video" if use_videos else "image",
            "shape": (image_size, image_size, 3),
            "names": ["height", "width", "channel"],
        }
    return features

ACTION_NAMES_DOC = (
    "[dx, dy, dz, qx, qy, qz, qw, gripper]: end-effector position delta in metres (robot base frame), "
    "rotation delta as a unit quaternion q_next * q_now^-1 with qw >= 0, gripper -1 open / +1 closed; "
    "|delta_pos| <= 0.05 m, rotation <= pi/40 rad"
)
