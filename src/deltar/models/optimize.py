"""Inference-time speed-ups that keep the outputs (to float rounding).

* Batch norms that directly follow a convolution are folded into its weights.
* Convolutions run in channels-last memory layout, which oneDNN prefers on CPU.
* TensorFlow-"same" convolutions pad symmetrically inside the convolution (no copy).
"""

from __future__ import annotations

import itertools

import torch
import torch.nn.functional as F
from torch import nn


def _fold_batch_norm(conv: nn.Conv1d | nn.Conv2d, norm: nn.modules.batchnorm._BatchNorm) -> None:
    """Fold an eval-mode batch norm into the preceding convolution, in place."""
    scale = norm.weight / torch.sqrt(norm.running_var + norm.eps)
    shape = (-1,) + (1,) * (conv.weight.ndim - 1)
    conv.weight.data = conv.weight.data * scale.reshape(shape)
    bias = conv.bias.data if conv.bias is not None else torch.zeros_like(norm.running_mean)
    new_bias = (bias - norm.running_mean) * scale + norm.bias
    conv.bias = nn.Parameter(new_bias.detach())


def _without_norm(norm: nn.Module) -> nn.Module:
    """What is left of a (possibly norm + activation) module once the norm is folded."""
    # timm's BatchNormAct2d applies batch norm, then ``drop``, then ``act``.
    tail = [getattr(norm, name) for name in ("drop", "act") if hasattr(norm, name)]
    tail = [module for module in tail if not isinstance(module, nn.Identity)]
    if not tail:
        return nn.Identity()
    return tail[0] if len(tail) == 1 else nn.Sequential(*tail)


@torch.no_grad()
def fuse_conv_batch_norm(model: nn.Module) -> int:
    """Fold every batch norm registered right after a convolution of matching width.

    Works on containers whose children are registered in data-flow order (timm's
    EfficientNet/MobileNet blocks, ``nn.Sequential``, this package's modules); the
    convolution's output must feed only that batch norm. Call on an eval-mode model.

    Args:
        model: module to modify in place.

    Returns:
        Number of batch norms folded.
    """
    if model.training:
        raise ValueError("fuse_conv_batch_norm needs an eval-mode model (call .eval())")
    folded = 0
    for parent in list(model.modules()):
        children = list(parent.named_children())
        for (_, first), (norm_name, second) in itertools.pairwise(children):
            is_conv = isinstance(first, (nn.Conv1d, nn.Conv2d))
            is_norm = isinstance(second, (nn.BatchNorm1d, nn.BatchNorm2d))
            if not (is_conv and is_norm) or second.num_features != first.out_channels:
                continue
            if not second.track_running_stats or second.running_var is None:
                continue
            _fold_batch_norm(first, second)
            setattr(parent, norm_name, _without_norm(second))
            folded += 1
    return folded


class SymmetricSameConv2d(nn.Conv2d):
    """TensorFlow-style "same" convolution without a padding copy: same outputs.

    timm's ``Conv2dSame`` zero-pads its input asymmetrically before every call (for a
    stride-2 convolution of an even size: one row and column more after than before),
    which costs a full copy of the input (on CPU, at 256x320, about as much as the
    convolution). Padding one more row before as well and leading the kernel with one
    row of zeros (per axis, where the padding is uneven) gives the same sums of the same
    pixels times the same weights (the extra taps multiply a neighbouring row by zero,
    so only a non-finite input value would reach further), and ``conv2d`` does
    symmetric padding itself.

    Args:
        conv: a ``timm.layers.Conv2dSame`` (dilation 1); its weight and bias are shared.
    """

    def __init__(self, conv: nn.Conv2d) -> None:
        # Built on the meta device (no memory, no draw from the random generator): the
        # parameters are the wrapped convolution's own.
        super().__init__(conv.in_channels, conv.out_channels, conv.kernel_size, conv.stride,
                         0, conv.dilation, conv.groups, conv.bias is not None,
                         device="meta", dtype=conv.weight.dtype)
        if tuple(conv.dilation) != (1, 1):
            raise ValueError(f"only dilation 1 is supported, got {conv.dilation}")
        self.weight = conv.weight
        self.bias = conv.bias

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C_in, H, W) -> (B, C_out, ceil(H / s), ceil(W / s)), TensorFlow "same"."""
        from timm.layers import get_same_padding

        pads, leads = [], []
        for size, kernel, stride in zip(x.shape[-2:], self.kernel_size, self.stride,
                                        strict=True):
            total = get_same_padding(size, kernel, stride, 1)
            after = total - total // 2
            pads.append(after)
            leads.append(after - total // 2)  # 0 or 1
        weight = self.weight
        if any(leads):
            layout = (torch.channels_last
                      if weight.is_contiguous(memory_format=torch.channels_last)
                      and not weight.is_contiguous() else torch.contiguous_format)
            weight = F.pad(weight, (leads[1], 0, leads[0], 0)).contiguous(memory_format=layout)
        return F.conv2d(x, weight, self.bias, self.stride, tuple(pads), 1, self.groups)


def use_symmetric_same_convs(model: nn.Module) -> int:
    """Replace every timm ``Conv2dSame`` (dilation 1) by :class:`SymmetricSameConv2d`.

    Returns:
        Number of convolutions replaced.
    """
    from timm.layers import Conv2dSame

    replaced = 0
    for parent in list(model.modules()):
        for name, child in list(parent.named_children()):
            if isinstance(child, Conv2dSame) and tuple(child.dilation) == (1, 1):
                setattr(parent, name, SymmetricSameConv2d(child))
                replaced += 1
    return replaced


def prepare_for_inference(
    model: nn.Module, fold_encoder: bool = True, channels_last: bool = True,
    symmetric_same: bool = True,
) -> nn.Module:
    """Eval mode, every batch norm folded and channels-last layout, in place.

    Each step changes results only by float rounding; the tests hold all of them together
    to the release's parity tolerance on its parity fixture, at several thread counts
    (their speed: benchmarks/RESULTS.md).

    Args:
        model: a :class:`~deltar.models.DeltarNet`.
        fold_encoder: also fold the image encoder's batch norms (not only the decoder's
            and the distribution encoder's).
        channels_last: convert the image encoder's, the decoder's and the head's 4-D
            weights to channels-last layout (oneDNN's fast path; the encoder's maps then
            come out channels-last whatever the input's layout).
        symmetric_same: run the encoder's TensorFlow-"same" convolutions without a
            padding copy (:class:`SymmetricSameConv2d`; the same depth to the bit in the
            tests).

    Returns:
        The same model, ready for ``torch.inference_mode()``.
    """
    model.eval()
    names = ["decoder", "distribution_encoder"] + (["image_encoder"] if fold_encoder else [])
    # Parts a model lacks (ablations without a distribution branch, test doubles) are skipped.
    for part in (getattr(model, name, None) for name in names):
        if part is not None:
            fuse_conv_batch_norm(part)
    if symmetric_same:
        use_symmetric_same_convs(model)
    if channels_last:
        for name in ("image_encoder", "decoder", "head"):
            part = getattr(model, name, None)
            if part is not None:
                part.to(memory_format=torch.channels_last)
    return model
