"""Where each signal lives in a recording: the topic map, with Intera (Sawyer, ROS 1) defaults.

Every entry can be overridden by flag (`--topics.joint_states=/my/joints`) or in a config file.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot_bcrl.robot.kinematics import SAWYER_ARM_JOINTS


@dataclass
class TopicMap:
    joint_states: str = "/robot/joint_states"  # sensor_msgs/JointState
    joint_names: list[str] = field(default_factory=lambda: list(SAWYER_ARM_JOINTS))  # arm joints, URDF order
    # geometry_msgs/PoseStamped of the tool in the base frame; "" (or absent from the bag) -> FK of joints
    eef_pose: str = "/robot/limb/right/endpoint_pose"
    # camera name -> sensor_msgs/Image topic; `<topic>/compressed` (CompressedImage) is used if only it exists.
    # The camera named "agentview" becomes observation.images.agentview, as in the simulated datasets.
    cameras: dict[str, str] = field(default_factory=lambda: {"agentview": "/camera/color/image_raw"})
    # Gripper: "joint" reads finger joints inside joint_states; "topic" reads a std_msgs Bool/Float64.
    gripper_source: str = "joint"
    gripper_joints: list[str] = field(
        default_factory=lambda: ["right_gripper_l_finger_joint", "right_gripper_r_finger_joint"]
    )
    # Closed when the opening (sum of |finger joint|) is below this (m). robosuite's Rethink gripper opens to
    # ~0.021 (dipping to ~0.014 while settling) and reads ~0.006 on the cube; set it per rig.
    gripper_closed_below: float = 0.012
    gripper_topic: str = "/bcrl/gripper_command"
    gripper_closed_above: float = 0.0  # Float64 above this -> closed (Bool: true -> closed)
    use_header_stamps: bool = True  # sensor time from header.stamp; False -> the bag's log time
