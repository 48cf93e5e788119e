"""The gradient check the sensor tests share: a parameter's derivative by autograd and by central differences."""

from __future__ import annotations

import torch


def autograd_and_difference(loss, parameter: torch.Tensor, eps: float) -> tuple[float, float]:
    """(d loss / d parameter by autograd, the same by central differences over +-``eps``) for a 0-d ``parameter``;
    ``loss()`` recomputes the 0-d loss from scratch. The parameter is left at its value."""
    parameter.grad = None
    loss().backward()
    autograd = float(parameter.grad)
    with torch.no_grad():
        parameter += eps
        plus = float(loss())
        parameter -= 2 * eps
        minus = float(loss())
        parameter += eps
    return autograd, (plus - minus) / (2 * eps)
