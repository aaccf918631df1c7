"""Sensor geometry and timing constants shared by every part of the project."""

from __future__ import annotations

from dataclasses import asdict, dataclass

__all__ = ["STEP_RATE_HZ", "STEP_SECONDS", "Layout", "DEFAULT_LAYOUT"]

#: Sensor sampling rate: one step (one 1-bit frame) every 25 us.
STEP_RATE_HZ = 40_000
STEP_SECONDS = 1.0 / STEP_RATE_HZ


@dataclass(frozen=True)
class Layout:
    """How upright frames of ``height x width`` pixels are stored as packed bytes.

    Parameters
    ----------
    width, height : int
        Image geometry in pixels (after dropping head columns).
    head_cols : int
        Extra columns stored at the right of every row (16 on some 400 x 250 captures,
        giving 416-bit rows); they are dropped on read and written as zeros.
    flipud : bool
        Rows are stored bottom-up (SpikeCV / Spike-Zoo convention, the default).
    fliplr : bool
        Columns are stored right-to-left (some setups; combined with flipud it is a 180 degree
        rotation).
    """

    width: int = 400
    height: int = 250
    head_cols: int = 0
    flipud: bool = True
    fliplr: bool = False

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"geometry must be positive, got {self.width} x {self.height}")
        if self.head_cols < 0:
            raise ValueError(f"head_cols must be >= 0, got {self.head_cols}")
        if (self.stored_width * self.height) % 8:
            raise ValueError(
                f"{self.stored_width} x {self.height} pixels is not a whole number of bytes"
            )

    @property
    def stored_width(self) -> int:
        """Pixels per stored row, head columns included."""
        return self.width + self.head_cols

    @property
    def frame_bytes(self) -> int:
        """Bytes per packed frame (12,500 for 400 x 250)."""
        return self.stored_width * self.height // 8

    @property
    def shape(self) -> tuple[int, int]:
        return (self.height, self.width)

    def to_dict(self) -> dict:
        return asdict(self)


DEFAULT_LAYOUT = Layout()
