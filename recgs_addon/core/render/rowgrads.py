"""Row-sparse gradients: a render touches few rows of a large model, so keep it that way.

:func:`recgs_addon.core.render.rasterizer.render` reads every per-Gaussian input only at the rows of
the Gaussians in view (``index_select(0, ids)``, about a sixth of the model on the sample
survey). Under plain autograd each of those reads has a full-size backward: a fresh zero
tensor as large as the parameter, then a scatter into it. On a 1.5M-Gaussian model with SH
degree 3 that is ~370 MB of new memory (zeroed, page by page) on every step, about a third
of the step time.

:class:`RowGrads` is passed to ``render`` as its ``gather``. The rows it gathers are copies
of their own, behind an identity function whose backward keeps their gradient in a slot;
after ``loss.backward()``, :meth:`RowGrads.write` copies those gradients into full-size
buffers that persist between steps (zero outside the rows written last) and sets them as
the parameters' ``.grad`` for the optimiser. The rows are unique, so the values are exactly
autograd's (``index_add`` into zeros is a copy), and a parameter that was not gathered, or
got no gradient, keeps ``grad = None`` as under autograd: training is the
same, bit for bit (tested).

Usage (one step)::

    rg = RowGrads()                                   # once; reuses its buffers
    sh_rest = rg.track("sh_rest", params["sh_rest"], cols=k - 1)
    means = rg.track("means", params["means"])        # ... every parameter render reads
    out = render(means, ..., gather=rg)
    loss.backward()
    rg.write()                                        # params[...].grad = full-size buffers
    optimizer.step(); optimizer.zero_grad(set_to_none=True)
"""
from __future__ import annotations

from typing import Optional

import torch


class _Collect(torch.autograd.Function):
    """Identity on gathered rows whose backward keeps the incoming gradient as it comes (a
    view of a concatenation's gradient, say) in a slot for :meth:`RowGrads.write`, instead
    of autograd copying it into a contiguous ``leaf.grad`` first (a full copy of ~300k rows
    of 45 SH coefficients per step on a large model)."""

    @staticmethod
    def forward(ctx, rows, slot):
        ctx.slot = slot
        return rows.view_as(rows)

    @staticmethod
    def backward(ctx, grad):
        slot = ctx.slot
        slot["grad"] = grad if slot["grad"] is None else slot["grad"] + grad
        return None, None


class RowGrads:
    """Gather rows of tracked parameters as leaves; write their gradients back (see module)."""

    def __init__(self, sparse: bool = True) -> None:
        #: False: plain autograd (``track`` is a no-op, ``write`` does nothing); for comparisons.
        self.sparse = sparse
        self._sources: dict[int, tuple] = {}    # id(tensor given to render) -> (name, param, cols, tensor)
        self._leaves: dict[str, tuple] = {}     # name -> (rows given to render, grad slot, ids, param, cols)
        self._buffers: dict[str, torch.Tensor] = {}
        self._written: dict[str, torch.Tensor] = {}   # name -> rows that are non-zero in its buffer

    def track(self, name: str, param: torch.Tensor, cols: Optional[int] = None) -> torch.Tensor:
        """The tensor to hand to ``render`` for ``param`` (``param[:, :cols]`` when ``cols``).

        Only the rows ``render`` gathers from it get gradients, through :meth:`write`.
        """
        x = param if cols is None else param[:, :cols]
        if not self.sparse:
            return x
        self._leaves.pop(name, None)
        self._sources[id(x)] = (name, param, cols, x)   # holding x keeps its id unique
        return x

    def __call__(self, x: torch.Tensor, ids: torch.Tensor) -> torch.Tensor:
        """``x[ids]``, differentiable into :meth:`write` for a tracked tensor, else plain
        index_select."""
        src = self._sources.get(id(x))
        if src is None:
            return x.index_select(0, ids)
        name, param, cols, _ = src
        if name in self._leaves:     # the same rows read twice (means: projection, view dirs)
            rows_out, _, rows, _, _ = self._leaves[name]
            if rows is ids or torch.equal(rows, ids):
                return rows_out
            raise ValueError(f"RowGrads: {name!r} gathered at two different row sets in one render")
        base = param.detach() if cols is None else param.detach()[:, :cols]
        leaf = base.index_select(0, ids).requires_grad_(param.requires_grad)
        slot = {"grad": None}
        rows_out = _Collect.apply(leaf, slot) if param.requires_grad else leaf
        self._leaves[name] = (rows_out, slot, ids, param, cols)
        return rows_out

    def write(self) -> None:
        """After ``backward``: set each gathered parameter's ``.grad`` to its full-size buffer
        holding the rows' gradients (zero elsewhere); then forget this render's leaves."""
        with torch.no_grad():
            for name, (_, slot, ids, param, cols) in self._leaves.items():
                if slot["grad"] is None:
                    continue
                buf = self._buffers.get(name)
                if (buf is None or buf.shape != param.shape or buf.dtype != param.dtype
                        or buf.device != param.device):
                    buf = torch.zeros_like(param, memory_format=torch.contiguous_format)
                    self._buffers[name] = buf
                elif name in self._written:
                    buf.index_fill_(0, self._written[name], 0.0)
                target = buf if cols is None else buf[:, :cols]
                target.index_copy_(0, ids, slot["grad"])
                self._written[name] = ids
                param.grad = buf
        self._leaves.clear()
        self._sources.clear()
