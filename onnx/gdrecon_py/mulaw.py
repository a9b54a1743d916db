"""GradNet's mu-law, mu = 16 (one definition for the model, the losses and the pipeline):

    C(x) = log(1 + mu x) / log(1 + mu),   S(x) = sign(x) C(|x|),   C^-1(y) = ((1 + mu)^y - 1) / mu.

`mulaw`, `mulaw_signed`, `mulaw_inv` take torch tensors (training, in the tensor's dtype) or
numpy arrays / scalars (numpy's result type); torch is never imported for numpy input.
`C`, `S`, `C_inv` are the reference pipeline's float32 numpy forms (what the Rust side
reproduces): C and S computed as numpy computes them, cast to float32; C^-1 computed in float64.
"""
import math
import sys

import numpy as np

MU = 16.0


def _torch_of(x):
    """The torch module when `x` is a torch tensor, else None."""
    torch = sys.modules.get("torch")
    return torch if torch is not None and isinstance(x, torch.Tensor) else None


def mulaw(x, mu=MU):
    """C(x) = log(1 + mu x) / log(1 + mu) (x >= 0)."""
    torch = _torch_of(x)
    if torch is not None:
        return torch.log1p(mu * x) / math.log1p(mu)
    return np.log1p(mu * x) / np.log1p(mu)


def mulaw_signed(x, mu=MU):
    """S(x) = sign(x) C(|x|)."""
    torch = _torch_of(x)
    if torch is not None:
        return torch.sign(x) * torch.log1p(mu * x.abs()) / math.log1p(mu)
    return np.sign(x) * np.log1p(mu * np.abs(x)) / np.log1p(mu)


def mulaw_inv(y, mu=MU):
    """C^-1(y) = ((1 + mu)^y - 1) / mu."""
    torch = _torch_of(y)
    if torch is not None:
        return torch.expm1(y * math.log1p(mu)) / mu
    return np.expm1(y * np.log1p(mu)) / mu


def C(x, mu=MU):
    """Pipeline form of `mulaw`: numpy, float32 result."""
    return mulaw(x, mu).astype(np.float32)


def S(x, mu=MU):
    """Pipeline form of `mulaw_signed`: numpy, float32 result."""
    return mulaw_signed(x, mu).astype(np.float32)


def C_inv(y, mu=MU):
    """Pipeline form of `mulaw_inv`: computed in float64, float32 result."""
    return mulaw_inv(np.asarray(y, np.float64), mu).astype(np.float32)
