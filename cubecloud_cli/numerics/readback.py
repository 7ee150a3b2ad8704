"""Scalars a training loop leaves on its device, read back to the host in groups (issue 54).

Reading a GPU tensor's value (``float(loss)``, ``bool(finite)``) makes the host wait until the
device has run every kernel queued so far, so the host cannot queue the next step while the
device runs this one: the two take turns. A trainer pushes each step's scalars here and reads
them every ``READ_EVERY_ON_GPU`` steps, or when it must know them (a log row, a checkpoint, a
change to the set of Gaussians). On a CPU there is nothing to overlap and each step is read at
once, so a CPU run behaves as before, to the bit.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

READ_EVERY_ON_GPU = 64


@dataclass
class GroupedReads:
    every: int = 1
    _pending: list[tuple[int, "torch.Tensor"]] = field(default_factory=list)

    @classmethod
    def for_device(cls, device: "torch.device") -> "GroupedReads":
        return cls(1 if device.type == "cpu" else READ_EVERY_ON_GPU)

    def push(self, iteration: int, values: "torch.Tensor") -> bool:
        """Queue iteration's 1-D tensor of scalars; returns whether a read is due."""
        self._pending.append((iteration, values))
        return len(self._pending) >= max(self.every, 1)

    def read(self) -> list[tuple[int, list[float]]]:
        """Every queued iteration with its scalars, in order, in one transfer; then empty."""
        if not self._pending:
            return []
        import torch

        rows = torch.stack([values for _, values in self._pending]).tolist()
        read = [(iteration, row) for (iteration, _), row in zip(self._pending, rows)]
        self._pending.clear()
        return read
