"""GradNet (Guo et al. 2019, "GradNet: Unsupervised Deep Screened Poisson Reconstruction for
Gradient-Domain Rendering"), as in the authors' PyTorch release (shared/REFERENCE-NOTES.md s. 2).

Every colour channel goes through the network on its own: a frame of H x W becomes a batch of
3 items (R, G, B) that share the feature buffers.

Inputs per item (all N x C x H x W, float32, H and W multiples of 8):
  data     : GradNet       8 channels  [C(I_c), albedo RGB, normal XYZ (0..1), depth (0..1)]
             GradNetNoFeat 1 channel   [C(I_c)]
  grad     : 2 channels  [S(dx_c), S(dy_c)]
Output: N x 1 x H x W, in the mu-law compressed domain (radiance = C^-1(out)).

C(x) = log(1 + mu x) / log(1 + mu), mu = 16; S(x) = sign(x) C(|x|) (gdrecon_py.mulaw).

The G-branch (`GBranch`, training only) maps concat(data, grad) (10 channels) to the 7-vector G
of the first-order loss. The losses are here too (`loss_data`, `loss_grad`, `loss_first_order`).
"""
import torch
import torch.nn as nn
import torch.nn.functional as F

from .mulaw import mulaw, mulaw_inv, mulaw_signed

N_FEAT = 7
LRELU = 0.01
# The encoder's and residual blocks' activation: the release's LeakyReLU (slope LRELU), or ReLU,
# which ONNX Runtime fuses into an int8 convolution (the int8 graph's variant, docs/gradnet.md,
# "A ReLU graph for int8"); the decoder's is ReLU in both.
ACTIVATIONS = ("leaky_relu", "relu")


def _act(activation):
    if activation not in ACTIVATIONS:
        raise ValueError(f"activation {activation!r} not in {ACTIVATIONS}")
    return nn.LeakyReLU(LRELU) if activation == "leaky_relu" else nn.ReLU()


def activation_of(meta):
    """An exported graph's encoder activation, from its metadata (`export.export_model` writes it
    for ReLU only; absent means the release's LeakyReLU)."""
    return meta.get("activation", "leaky_relu")


# ------------------------------------------------------------------------------------------
# network

def _down(cin, cout, activation):
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride=2, padding=1), _act(activation))


def _up(cin, cout):
    return nn.Sequential(nn.ConvTranspose2d(cin, cout, 4, stride=2, padding=1), nn.ReLU())


class ResBlock(nn.Module):
    def __init__(self, ch, activation="leaky_relu"):
        super().__init__()
        self.c1 = nn.Conv2d(ch, ch, 3, padding=1)
        self.c2 = nn.Conv2d(ch, ch, 3, padding=1)
        self.relu = activation == "relu"

    def forward(self, x):
        y = self.c1(x)
        return x + self.c2(F.relu(y) if self.relu else F.leaky_relu(y, LRELU))


class GradNet(nn.Module):
    """Two-branch encoder (data / gradient), 4 residual blocks at 256 channels, decoder of
    transposed convs with dual skip connections. `data_ch` = 8 (full) or 1 (no features);
    `activation` (ACTIVATIONS) the encoder's and residual blocks'; the parameters are the same
    for both."""

    def __init__(self, data_ch=1 + N_FEAT, grad_ch=2, n_res=4, activation="leaky_relu"):
        super().__init__()
        self.data_ch = data_ch
        self.activation = activation
        a = activation
        self.d1, self.d2, self.d3 = _down(data_ch, 32, a), _down(32, 64, a), _down(64, 128, a)
        self.g1, self.g2, self.g3 = _down(grad_ch, 32, a), _down(32, 64, a), _down(64, 128, a)
        self.res = nn.Sequential(*[ResBlock(256, a) for _ in range(n_res)])
        self.u1 = _up(512, 128)
        self.u2 = _up(256, 64)
        self.u3 = _up(128, 32)
        self.out = nn.Conv2d(32, 1, 3, padding=1)

    def forward(self, data, grad):
        d1 = self.d1(data)
        d2 = self.d2(d1)
        d3 = self.d3(d2)
        g1 = self.g1(grad)
        g2 = self.g2(g1)
        g3 = self.g3(g2)
        r = self.res(torch.cat([d3, g3], 1))
        u = self.u1(torch.cat([r, d3, g3], 1))
        u = self.u2(torch.cat([u, d2, g2], 1))
        u = self.u3(torch.cat([u, d1, g1], 1))
        return F.relu(self.out(u))


def GradNetNoFeat():
    """The paper's L_d+g variant: colour + gradients only (data branch gets C(I_c) alone)."""
    return GradNet(data_ch=1)


class GBranch(nn.Module):
    """Training-only branch predicting the first-order derivative G (7 per pixel)."""

    def __init__(self, in_ch=1 + N_FEAT + 2, n_feat=N_FEAT):
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(in_ch, 64, 3, padding=1), nn.LeakyReLU(LRELU),
            nn.Conv2d(64, 64, 3, padding=1), nn.LeakyReLU(LRELU),
            nn.Conv2d(64, n_feat, 3, padding=1))

    def forward(self, data, grad):
        return self.net(torch.cat([data, grad], 1))


def n_params(m):
    return sum(p.numel() for p in m.parameters())


# ------------------------------------------------------------------------------------------
# losses (means over all elements; y = network output, compressed; tensors N x 1 x H x W)

def loss_data(y, color):
    """L_data = mean |y - C(I)|, I = linear noisy channel."""
    return (y - mulaw(color)).abs().mean()


def loss_grad(y, dx, dy):
    """L_grad = mean |S(D_x C^-1(y)) - S(dx)| + mean |S(D_y C^-1(y)) - S(dy)| over the W-1 / H-1
    valid forward differences."""
    lin = mulaw_inv(y)
    gx = lin[..., :, 1:] - lin[..., :, :-1]
    gy = lin[..., 1:, :] - lin[..., :-1, :]
    lx = (mulaw_signed(gx) - mulaw_signed(dx[..., :, :-1])).abs().mean()
    ly = (mulaw_signed(gy) - mulaw_signed(dy[..., :-1, :])).abs().mean()
    return lx + ly


def loss_first_order(y, feat, G, color):
    """First-order loss (paper Eq. 10), both directions, both signs, 4-neighbourhood:
    for a pair (p, q) of horizontal or vertical neighbours,
        w |(y(q) - y(p)) - G(p).(F(q) - F(p))| + w |(y(p) - y(q)) - G(q).(F(p) - F(q))|,
    w = exp(-9 (I(q) - I(p))^2) on the linear noisy channel I (sigma_b^2 = 1/18).
    Returns the sum of the four means (right/left/down/up terms). y: N1HW, feat: N7HW,
    G: N7HW, color: N1HW."""
    total = 0.0
    for axis in (3, 2):
        n = y.shape[axis]
        sl_p = [slice(None)] * 4
        sl_q = [slice(None)] * 4
        sl_p[axis] = slice(0, n - 1)
        sl_q[axis] = slice(1, n)
        sl_p, sl_q = tuple(sl_p), tuple(sl_q)
        dyv = y[sl_q] - y[sl_p]
        dF = feat[sl_q] - feat[sl_p]
        w = torch.exp(-9.0 * (color[sl_q] - color[sl_p]) ** 2)
        t_fwd = (dyv - (G[sl_p] * dF).sum(1, keepdim=True)).abs()
        t_bwd = (-dyv - (G[sl_q] * (-dF)).sum(1, keepdim=True)).abs()
        total = total + (w * t_fwd).mean() + (w * t_bwd).mean()
    return total


# ------------------------------------------------------------------------------------------
# input assembly (per frame -> per-channel batch), tensors only; pipeline.py does the numpy side

def make_inputs(color, dx, dy, feat=None):
    """color/dx/dy: B x 3 x H x W (linear, sanitised), feat: B x 7 x H x W normalised or None.
    Returns (data, grad) with batch 3B ordered frame-major (frame0 R, frame0 G, frame0 B, ...)."""
    B, _, H, W = color.shape
    c = mulaw(color.clamp_min(0)).reshape(B * 3, 1, H, W)
    g = torch.stack([mulaw_signed(dx), mulaw_signed(dy)], 2).reshape(B * 3, 2, H, W)
    if feat is None:
        return c, g
    f = feat.unsqueeze(1).expand(B, 3, N_FEAT, H, W).reshape(B * 3, N_FEAT, H, W)
    return torch.cat([c, f], 1), g
