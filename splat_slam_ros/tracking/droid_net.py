"""The DROID-SLAM recurrent network in plain torch (paper Sec. 3.1, "flow and confidence").

Splat-SLAM's tracking predicts, for every edge (i, j) of the keyframe graph, a
dense correction of the optical flow and a per-pixel confidence with DROID-SLAM's
recurrent update operator. This module re-implements that network so that the
public checkpoint (``droid.pth``) loads into it unchanged: the sub-module and
parameter names and shapes follow the public model's state-dict layout
(``fnet.*``, ``cnet.*``, ``update.*``). Nothing here needs a compiled extension:
the correlation lookup, done by a CUDA kernel in the reference, is bilinear
sampling with ``grid_sample`` here and runs on CPU or CUDA.

Pieces (all at 1/8 of the input image):

* :class:`Encoder` - the feature encoder ``fnet`` (128-d, instance norm) and the
  context encoder ``cnet`` (256-d, no norm; split into the GRU's initial hidden
  state ``net`` = tanh and its static input ``inp`` = relu).
* :class:`CorrPyramid` - all-pairs correlation of two feature maps, average
  pooled 4 times over the target image, looked up in a 7x7 window (radius 3)
  around the current correspondence at every level (4 x 49 = 196 channels).
* :class:`UpdateOperator` - correlation/motion encoders, the ConvGRU with its
  global context gates, the flow-delta and confidence heads and the graph
  aggregation (``agg``) that pools the hidden states of all edges leaving the
  same keyframe into the damping ``eta`` and the 8x upsampling mask.
* :func:`iterate_edges` - the factor-graph iteration: every edge keeps a GRU
  state, correlation features are looked up at the current correspondence,
  the motion features are ``[coords1 - coords0, target - coords1]`` and the
  operator's delta moves the target (Eq. 1's ``p*_ij``, weights ``w_ij``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import List, Optional

import torch
import torch.nn as nn
import torch.nn.functional as F

FEATURE_DIM = 128                      # fnet output channels
CONTEXT_DIM = 256                      # cnet output channels (hidden 128 + input 128)
HIDDEN_DIM = 128
CORR_LEVELS = 4
CORR_RADIUS = 3
CORR_CHANNELS = CORR_LEVELS * (2 * CORR_RADIUS + 1) ** 2      # 196
STRIDE = 8                             # the network works at 1/8 of the image
BASE = 32                              # encoder width after the first convolution
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


# --------------------------------------------------------------------------- encoders
def _norm(kind: str, channels: int) -> nn.Module:
    """'instance' (no affine parameters, as in the checkpoint) or 'none'."""
    if kind == "instance":
        return nn.InstanceNorm2d(channels)
    if kind == "none":
        return nn.Sequential()
    raise ValueError(f"unsupported encoder normalisation {kind!r}")


class ResBlock(nn.Module):
    """Two 3x3 convolutions with a (strided 1x1) skip path."""

    def __init__(self, cin: int, cout: int, norm: str, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride=stride, padding=1)
        self.conv2 = nn.Conv2d(cout, cout, 3, padding=1)
        self.norm1 = _norm(norm, cout)
        self.norm2 = _norm(norm, cout)
        self.downsample: Optional[nn.Module] = None
        if stride != 1:
            self.norm3 = _norm(norm, cout)
            self.downsample = nn.Sequential(nn.Conv2d(cin, cout, 1, stride=stride), self.norm3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.norm1(self.conv1(x)))
        y = F.relu(self.norm2(self.conv2(y)))
        skip = x if self.downsample is None else self.downsample(x)
        return F.relu(skip + y)


class Encoder(nn.Module):
    """7x7/2 stem, three stages of two residual blocks (strides 1, 2, 2), 1x1 head."""

    def __init__(self, out_dim: int, norm: str):
        super().__init__()
        self.conv1 = nn.Conv2d(3, BASE, 7, stride=2, padding=3)
        self.norm1 = _norm(norm, BASE)
        self.layer1 = nn.Sequential(ResBlock(BASE, BASE, norm, 1), ResBlock(BASE, BASE, norm))
        self.layer2 = nn.Sequential(ResBlock(BASE, 2 * BASE, norm, 2),
                                    ResBlock(2 * BASE, 2 * BASE, norm))
        self.layer3 = nn.Sequential(ResBlock(2 * BASE, 4 * BASE, norm, 2),
                                    ResBlock(4 * BASE, 4 * BASE, norm))
        self.conv2 = nn.Conv2d(4 * BASE, out_dim, 1)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(N, 3, H, W) normalised images -> (N, out_dim, H/8, W/8)."""
        x = F.relu(self.norm1(self.conv1(x)))
        x = self.layer3(self.layer2(self.layer1(x)))
        return self.conv2(x)


# --------------------------------------------------------------------------- correlation
def coords_grid(h: int, w: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """(h, w, 2) pixel coordinates (x, y) of the 1/8 grid."""
    y, x = torch.meshgrid(torch.arange(h, device=device, dtype=dtype),
                          torch.arange(w, device=device, dtype=dtype), indexing="ij")
    return torch.stack([x, y], -1)


class CorrPyramid:
    """All-pairs correlation volumes of E edges, pooled over the target image.

    ``volume[e, y, x, v, u] = <f_i(y, x), f_j(v, u)> / 16`` (features scaled by
    1/4 each, as the checkpoint was trained); level k averages 2^k x 2^k target
    pixels. :meth:`lookup` samples a (2r+1)^2 window around ``coords / 2^k``
    bilinearly with zeros outside the image; channels are ordered x-offset major
    (index ``dx * 7 + dy``) as the reference CUDA kernel writes them.
    """

    def __init__(self, levels: List[torch.Tensor], radius: int = CORR_RADIUS):
        self.levels = levels                       # each (E*h*w, 1, h_k, w_k)
        self.radius = radius

    @staticmethod
    def volume(f1: torch.Tensor, f2: torch.Tensor) -> torch.Tensor:
        """(E, C, h, w) x (E, C, h, w) -> (E, h*w, h*w)."""
        E, C, h, w = f1.shape
        a = f1.reshape(E, C, h * w) / 4.0
        b = f2.reshape(E, C, h * w) / 4.0
        return torch.bmm(a.transpose(1, 2), b)

    @classmethod
    def from_volume(cls, vol: torch.Tensor, h: int, w: int,
                    num_levels: int = CORR_LEVELS) -> "CorrPyramid":
        E = vol.shape[0]
        c = vol.reshape(E * h * w, 1, h, w)
        levels = [c]
        for _ in range(num_levels - 1):
            c = F.avg_pool2d(c, 2, stride=2)
            levels.append(c)
        return cls(levels)

    @classmethod
    def pair(cls, f_a: torch.Tensor, f_b: torch.Tensor) -> "CorrPyramid":
        """Pyramid of the two edges a -> b and b -> a (in that order) from one matrix
        product: the b -> a volume is the transpose of the a -> b one."""
        C, h, w = f_a.shape
        vol = cls.volume(f_a[None], f_b[None])[0]
        return cls.from_volume(torch.stack([vol, vol.t()]), h, w)

    @staticmethod
    def cat(pyrs: List["CorrPyramid"]) -> "CorrPyramid":
        """Edges of several pyramids in one (batched lookups)."""
        return CorrPyramid([torch.cat([p.levels[k] for p in pyrs], 0)
                            for k in range(len(pyrs[0].levels))], pyrs[0].radius)

    def lookup(self, coords: torch.Tensor) -> torch.Tensor:
        """coords (E, h, w, 2) target positions (1/8 px) -> (E, 196, h, w) features."""
        E, h, w, _ = coords.shape
        r = self.radius
        d = torch.arange(-r, r + 1, device=coords.device, dtype=coords.dtype)
        dx, dy = torch.meshgrid(d, d, indexing="ij")           # [a, b]: x offset a, y offset b
        offs = torch.stack([dx, dy], -1)                         # (2r+1, 2r+1, 2)
        c = coords.reshape(E * h * w, 1, 1, 2)
        out = []
        for k, vol in enumerate(self.levels):
            hk, wk = vol.shape[-2:]
            p = c / (2 ** k) + offs                              # (N, 2r+1, 2r+1, 2)
            g = torch.stack([2.0 * p[..., 0] / max(wk - 1, 1) - 1.0,
                             2.0 * p[..., 1] / max(hk - 1, 1) - 1.0], -1)
            s = F.grid_sample(vol, g.to(vol.dtype), mode="bilinear", padding_mode="zeros",
                              align_corners=True)               # (N, 1, 2r+1, 2r+1)
            out.append(s.reshape(E, h, w, -1))
        return torch.cat(out, -1).permute(0, 3, 1, 2).contiguous()


# --------------------------------------------------------------------------- update operator
class ConvGRU(nn.Module):
    """Convolutional GRU whose gates also see a gated global average of the state."""

    def __init__(self, hidden: int = HIDDEN_DIM, inputs: int = 320):
        super().__init__()
        self.convz = nn.Conv2d(hidden + inputs, hidden, 3, padding=1)
        self.convr = nn.Conv2d(hidden + inputs, hidden, 3, padding=1)
        self.convq = nn.Conv2d(hidden + inputs, hidden, 3, padding=1)
        self.w = nn.Conv2d(hidden, hidden, 1)
        self.convz_glo = nn.Conv2d(hidden, hidden, 1)
        self.convr_glo = nn.Conv2d(hidden, hidden, 1)
        self.convq_glo = nn.Conv2d(hidden, hidden, 1)

    def forward(self, h: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        hx = torch.cat([h, x], 1)
        glo = (torch.sigmoid(self.w(h)) * h).mean(dim=(2, 3), keepdim=True)
        z = torch.sigmoid(self.convz(hx) + self.convz_glo(glo))
        r = torch.sigmoid(self.convr(hx) + self.convr_glo(glo))
        q = torch.tanh(self.convq(torch.cat([r * h, x], 1)) + self.convq_glo(glo))
        return (1 - z) * h + z * q


class GraphAgg(nn.Module):
    """Mean of the edges' hidden states per source keyframe -> damping and upsampling mask."""

    def __init__(self):
        super().__init__()
        self.conv1 = nn.Conv2d(HIDDEN_DIM, 128, 3, padding=1)
        self.conv2 = nn.Conv2d(128, 128, 3, padding=1)
        self.eta = nn.Sequential(nn.Conv2d(128, 1, 3, padding=1))
        self.upmask = nn.Sequential(nn.Conv2d(128, STRIDE * STRIDE * 9, 1))

    def forward(self, net: torch.Tensor, ii: torch.Tensor):
        """net (E, 128, h, w), ii (E,) source ids -> eta (K, h, w), upmask (K, 576, h, w)
        for the K distinct sources in ``torch.unique(ii)`` order."""
        _, ix = torch.unique(ii, return_inverse=True)
        K = int(ix.max()) + 1
        x = F.relu(self.conv1(net))
        s = torch.zeros((K,) + x.shape[1:], device=x.device, dtype=x.dtype).index_add_(0, ix, x)
        n = torch.bincount(ix, minlength=K).to(x.dtype).view(K, 1, 1, 1)
        x = F.relu(self.conv2(s / n))
        eta = 0.01 * F.softplus(self.eta(x))[:, 0]
        return eta, self.upmask(x)


class UpdateOperator(nn.Module):
    """One recurrent step: correlation + motion features -> GRU -> (delta, weight)."""

    def __init__(self):
        super().__init__()
        self.corr_encoder = nn.Sequential(
            nn.Conv2d(CORR_CHANNELS, 128, 1), nn.ReLU(inplace=True),
            nn.Conv2d(128, 128, 3, padding=1), nn.ReLU(inplace=True))
        self.flow_encoder = nn.Sequential(
            nn.Conv2d(4, 128, 7, padding=3), nn.ReLU(inplace=True),
            nn.Conv2d(128, 64, 3, padding=1), nn.ReLU(inplace=True))
        self.weight = nn.Sequential(
            nn.Conv2d(128, 128, 3, padding=1), nn.ReLU(inplace=True),
            nn.Conv2d(128, 2, 3, padding=1))
        self.delta = nn.Sequential(
            nn.Conv2d(128, 128, 3, padding=1), nn.ReLU(inplace=True),
            nn.Conv2d(128, 2, 3, padding=1))
        self.gru = ConvGRU(HIDDEN_DIM, 128 + 128 + 64)
        self.agg = GraphAgg()

    def forward(self, net, inp, corr, motion):
        """net/inp (E, 128, h, w), corr (E, 196, h, w), motion (E, 4, h, w) ->
        net, delta (E, h, w, 2) in 1/8 px, weight (E, h, w, 2) in (0, 1)."""
        x = torch.cat([inp, self.corr_encoder(corr), self.flow_encoder(motion)], 1)
        net = self.gru(net, x)
        delta = self.delta(net).permute(0, 2, 3, 1)
        weight = torch.sigmoid(self.weight(net)).permute(0, 2, 3, 1)
        return net, delta.contiguous(), weight.contiguous()


class DroidNet(nn.Module):
    """fnet + cnet + update, named as in the public checkpoint."""

    def __init__(self):
        super().__init__()
        self.fnet = Encoder(FEATURE_DIM, "instance")
        self.cnet = Encoder(CONTEXT_DIM, "none")
        self.update = UpdateOperator()

    @staticmethod
    def normalize(images: torch.Tensor) -> torch.Tensor:
        """(N, H, W, 3) uint8 RGB -> (N, 3, H, W) ImageNet-normalised float."""
        x = images.permute(0, 3, 1, 2).float() / 255.0
        mean = torch.tensor(IMAGENET_MEAN, device=x.device).view(1, 3, 1, 1)
        std = torch.tensor(IMAGENET_STD, device=x.device).view(1, 3, 1, 1)
        return (x - mean) / std

    def features(self, images: torch.Tensor):
        """(N, H, W, 3) uint8 RGB -> fmap (N, 128, h, w), net, inp (N, 128, h, w) each."""
        x = self.normalize(images)
        fmap = self.fnet(x)
        net, inp = self.cnet(x).split([HIDDEN_DIM, HIDDEN_DIM], 1)
        return fmap, torch.tanh(net), torch.relu(inp)


@dataclass
class EdgeResult:
    """Outcome of :func:`iterate_edges` for E edges."""
    target: torch.Tensor          # (E, h, w, 2) predicted correspondences p*_ij (1/8 px)
    weight: torch.Tensor          # (E, h, w, 2) confidences w_ij in (0, 1)
    net: torch.Tensor             # (E, 128, h, w) final GRU states
    eta: torch.Tensor             # (K, h, w) damping per distinct source keyframe
    upmask: torch.Tensor          # (K, 576, h, w) convex upsampling mask logits


def iterate_edges(update: UpdateOperator, corr: CorrPyramid, net: torch.Tensor,
                  inp: torch.Tensor, coords1: torch.Tensor, ii: torch.Tensor,
                  iters: int) -> EdgeResult:
    """The factor-graph iteration over E edges without the BA in between.

    ``coords1`` (E, h, w, 2) is the initial correspondence (the reprojection by the
    current estimate, or the identity). Each step looks up the correlation at
    ``coords1``, encodes the motion ``[coords1 - coords0, target - coords1]``
    (clamped to +-64 as in training), runs the GRU and sets
    ``target = coords1 + delta`` (Eq. 1's p*_ij). Where the reference re-projects
    ``coords1`` from the bundle-adjusted poses, the correspondence follows the
    prediction here (``coords1 = target``): BA runs afterwards in the tracker on
    the returned (target, weight). The graph aggregation runs on the final states.
    """
    E, h, w, _ = coords1.shape
    coords0 = coords_grid(h, w, coords1.device, coords1.dtype)[None]
    target = coords1
    weight = torch.zeros_like(coords1)
    for _ in range(max(int(iters), 1)):
        feats = corr.lookup(coords1)
        motion = torch.cat([coords1 - coords0, target - coords1], -1)
        motion = motion.permute(0, 3, 1, 2).clamp(-64.0, 64.0)
        net, delta, weight = update(net, inp, feats, motion)
        target = coords1 + delta                                  # Eq. 1: p*_ij
        coords1 = target
    eta, upmask = update.agg(net, ii)
    return EdgeResult(target=target, weight=weight, net=net, eta=eta, upmask=upmask)
