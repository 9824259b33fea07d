"""Features extractors for agent observations of more than one dimension (SB3's habit)."""

from __future__ import annotations

from collections.abc import Sequence

import torch as th
from gymnasium import spaces
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn


class AgentViewCNN(BaseFeaturesExtractor):
    """Small CNN for channel-last local views ``(H, W, C)``, such as MAgent2's ``(13, 13, 5)``.

    Layout: height, width, then channels last (MAgent2's and PettingZoo's image layout; SB3's
    ``NatureCNN`` expects channels first instead). The view is permuted to ``(C, H, W)`` and goes
    through 3x3 convolutions with padding 1 (the spatial size is kept, so views of any size work),
    each followed by ReLU, then ``ReLU(Linear(-> features_dim))``. Values are used as the env gives
    them (cast to float32, not rescaled): scale ``uint8`` pixel views in the env if they need it.

    :param observation_space: one agent's ``Box`` of shape ``(H, W, C)``.
    :param features_dim: output features per agent.
    :param channels: output channels of each convolution.
    """

    def __init__(
        self, observation_space: spaces.Box, features_dim: int = 64, channels: Sequence[int] = (32, 32)
    ) -> None:
        if not isinstance(observation_space, spaces.Box) or len(observation_space.shape) != 3:
            raise ValueError(
                "AgentViewCNN reads channel-last views: a Box of shape (height, width, channels), got "
                f"{observation_space}."
            )
        if not channels or min(channels) < 1:
            raise ValueError(f"channels must be positive convolution widths, got {channels!r}.")
        super().__init__(observation_space, features_dim)
        height, width, in_channels = observation_space.shape
        layers: list[nn.Module] = []
        for out_channels in channels:
            layers += [nn.Conv2d(in_channels, out_channels, kernel_size=3, padding=1), nn.ReLU()]
            in_channels = out_channels
        self.cnn = nn.Sequential(*layers, nn.Flatten())
        self.linear = nn.Sequential(nn.Linear(in_channels * height * width, features_dim), nn.ReLU())

    def forward(self, observations: th.Tensor) -> th.Tensor:
        """The features of channel-last views.

        :param observations: ``(batch, H, W, C)``.
        :return: ``(batch, features_dim)``.
        """
        return self.linear(self.cnn(observations.permute(0, 3, 1, 2)))
