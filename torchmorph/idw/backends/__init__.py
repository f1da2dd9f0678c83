"""The backends of IDW, one per way of doing the kernel work, behind one
:class:`Backend` protocol: :mod:`~torchmorph.idw.backends.torch` (torch operations: the
baseline, runs everywhere, differentiable and traceable), :mod:`~torchmorph.idw.backends.triton`
(fused kernels on CUDA) and :mod:`~torchmorph.idw.backends.numba` (fused kernels on the
CPU). The table that picks one per call is in :mod:`torchmorph.idw._dispatch`."""

from torchmorph.idw.backends._protocol import Backend, power_code

__all__ = ["Backend", "power_code"]
