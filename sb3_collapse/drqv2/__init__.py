"""DrQ-v2 for Stable-Baselines3: algorithm, policies, augmentation, exploration schedules and replay buffer."""

from sb3_collapse.common.layers import LAYER_NAMES
from sb3_collapse.drqv2.augmentation import random_shift
from sb3_collapse.drqv2.drqv2 import DrQv2
from sb3_collapse.drqv2.policies import CnnPolicy, DrQv2Policy, MlpPolicy, MultiInputPolicy
from sb3_collapse.drqv2.replay_buffer import FrameStackReplayBuffer
from sb3_collapse.drqv2.schedules import StddevSchedule

__all__ = [
    "LAYER_NAMES",
    "CnnPolicy",
    "DrQv2",
    "DrQv2Policy",
    "FrameStackReplayBuffer",
    "MlpPolicy",
    "MultiInputPolicy",
    "StddevSchedule",
    "random_shift",
]
