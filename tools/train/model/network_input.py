"""What every network here takes in: a square image of the input channels (contracts.fields.INPUT_CHANNELS,
baseline RGB then current RGB, each in [0, 1]). The architectures' configs extend it with their own sizes."""
from __future__ import annotations

from dataclasses import dataclass

from ....contracts.fields import INPUT_CHANNELS

IN_CHANS = len(INPUT_CHANNELS)


@dataclass(frozen=True)
class NetworkInput:
    image_size: int = 128      # pixels per side (DESIGN §10 small CPU configuration)
    in_chans: int = IN_CHANS
