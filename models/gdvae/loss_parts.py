"""Named loss terms that do not hold the accelerator up.

Reading a loss as a Python float waits for the device to finish everything queued before it. A
training step that reads its dozen terms that way stops the GPU a dozen times per iteration, and a
small model's step then costs its synchronisations, not its arithmetic. Here each term stays a
detached tensor until it is read: the training loops read them when they log, and feed the
learning-rate schedule tensors it averages on the device.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping

import torch


class LossParts(Mapping):
    """name -> float, each read from its detached tensor when asked for (`tensor` gives the
    tensor itself without waiting)."""

    def __init__(self, terms: dict[str, torch.Tensor | float]):
        self.terms = {name: value.detach() if isinstance(value, torch.Tensor) else value
                      for name, value in terms.items()}

    def __getitem__(self, name: str) -> float:
        return float(self.terms[name])

    def __iter__(self) -> Iterator[str]:
        return iter(self.terms)

    def __len__(self) -> int:
        return len(self.terms)

    def tensor(self, name: str) -> torch.Tensor | float:
        return self.terms[name]
