"""Data-parallel rendering over several processes or machines with ``torch.distributed`` (gloo on the CPU; with
CUDA tensors NCCL, each rank on its own GPU: :func:`process_group_backend`, :func:`rank_device`).

Every rank holds the whole medium (the grids are small next to the work of tracing them) and traces a fixed
interleaved share of the sensor elements: element t belongs to rank ``t % world``. The random numbers of a path are
keyed by the global element index, so the shares sum to exactly the single-process image. The forward image is
combined with one ``all_reduce`` (sum) and is then the same on every rank; in the backward pass each rank replays
only its own paths and the gradients of σ_t and albedo are combined with one ``all_reduce`` each, so every rank
takes the same optimiser step. Nothing else changes: the loss, the optimiser and the parameters stay replicated.

Communication per iteration: the image (sensor elements × 3 values) forward, and 2 × 3·D·H·W values backward
(σ_t and albedo gradients), in the grids' dtype. Memory per rank: the grids, their gradient buffers (one per
thread inside the tracer) and the image.

Usage (on one machine with 2 processes: ``torchrun --nproc_per_node 2 script.py``; on several machines
``torchrun --nnodes N --node_rank K --nproc_per_node P --rdzv_endpoint HOST:PORT script.py``)::

    import torch.distributed as dist
    from torch_appearance import distributed
    dist.init_process_group("gloo")
    image = distributed.render(torch_appearance.render_scene, scene, sigma_t=sigma_t, albedo=albedo, spp=32, seed=it)
    loss(image).backward()          # sigma_t.grad / albedo.grad (and the parameters') equal on every rank
"""
import torch

__all__ = ["rank_and_world", "render", "all_reduce_sum", "reduce_gradient", "process_group_backend", "rank_device",
           "init_process_group"]


def process_group_backend(device):
    """The ``torch.distributed`` backend of a run whose tensors live on ``device``: ``"gloo"`` for the CPU; for a
    CUDA device ``"cpu:gloo,cuda:nccl"``: CUDA tensors are reduced by NCCL, and the CPU tensors such a run still
    reduces (the renders of a quantised print, which stay on the CPU) by gloo.

    Example:
        >>> process_group_backend("cpu"), process_group_backend(torch.device("cuda", 1))
        ('gloo', 'cpu:gloo,cuda:nccl')
    """
    from .checks import check_device

    return "cpu:gloo,cuda:nccl" if check_device("device", device).type == "cuda" else "gloo"


def rank_device(device, environ=None):
    """The device of this rank of a run on ``device``: the CPU stays the CPU; with CUDA each rank takes one GPU,
    ``cuda:LOCAL_RANK`` (``torchrun`` sets ``LOCAL_RANK``, the rank's number on its machine; 0 when absent), whatever
    index ``device`` names.

    Example:
        >>> rank_device("cuda", {"LOCAL_RANK": "3"}), rank_device("cpu", {"LOCAL_RANK": "3"})
        (device(type='cuda', index=3), device(type='cpu'))
    """
    import os

    from .checks import check_device

    device = check_device("device", device)
    if device.type != "cuda":
        return device
    environ = os.environ if environ is None else environ
    text = environ.get("LOCAL_RANK", "0")
    if not str(text).isdigit():
        raise ValueError(f"LOCAL_RANK: expected an int >= 0 (torchrun sets it), got {text!r}")
    return torch.device("cuda", int(text))


def init_process_group(device):
    """Start the default process group for a run on ``device`` (under ``torchrun``: ``RANK``, ``WORLD_SIZE`` and
    the rendezvous from the environment) with :func:`process_group_backend`; with CUDA this rank's GPU
    (:func:`rank_device`) becomes torch's current device first. Returns the rank's device."""
    import torch.distributed as dist

    device = rank_device(device)
    if device.type == "cuda":
        torch.cuda.set_device(device)
    dist.init_process_group(process_group_backend(device))
    return device


def rank_and_world(group=None):
    """(rank, world size) of the default (or given) process group, or (0, 1) when torch.distributed is not
    initialised."""
    import torch.distributed as dist

    if not (dist.is_available() and dist.is_initialized()):
        return 0, 1
    return dist.get_rank(group), dist.get_world_size(group)


class _AllReduceSum(torch.autograd.Function):
    """Sum over ranks forward; the gradient of each rank's share is the (replicated) gradient of the sum."""

    @staticmethod
    def forward(ctx, x, group):
        import torch.distributed as dist

        out = x.detach().clone()
        dist.all_reduce(out, op=dist.ReduceOp.SUM, group=group)
        return out

    @staticmethod
    def backward(ctx, grad):
        return grad, None


class _ReduceGradient(torch.autograd.Function):
    """Identity forward; the gradient is summed over ranks (each rank's replay covers its share of the paths)."""

    @staticmethod
    def forward(ctx, x, group):
        ctx.group = group
        return x.view_as(x)

    @staticmethod
    def backward(ctx, grad):
        import torch.distributed as dist

        grad = grad.contiguous().clone()
        dist.all_reduce(grad, op=dist.ReduceOp.SUM, group=ctx.group)
        return grad, None


def all_reduce_sum(x, group=None):
    """Differentiable sum of ``x`` over the ranks (identity when not distributed)."""
    return x if rank_and_world(group)[1] == 1 else _AllReduceSum.apply(x, group)


def reduce_gradient(x, group=None):
    """``x`` unchanged, its gradient summed over the ranks (identity when not distributed)."""
    if rank_and_world(group)[1] == 1 or not x.requires_grad:
        return x
    return _ReduceGradient.apply(x, group)


def render(render_fn, *args, sigma_t=None, albedo=None, group=None, **kwargs):
    """Data-parallel ``render_fn``: :func:`torch_appearance.render_scene`, :func:`torch_appearance.render_texels`, or
    the forward-only :func:`torch_appearance.render.render_scene_indexed`.

    The medium is named, not guessed: ``sigma_t`` and ``albedo`` go by keyword, are passed to ``render_fn`` under
    those names, and their gradients are summed over the ranks. Every argument must be the same on every rank (seed
    included). Returns the full image on every rank, differentiable; without torch.distributed it is just
    ``render_fn(*args, sigma_t=sigma_t, albedo=albedo, **kwargs)``.

    Args:
        render_fn: ``render_scene(scene, sigma_t, albedo, ...)``, ``render_texels(sigma_t, albedo, ...)`` or any
            function with the ``partition=(rank, world)`` keyword.
        args: ``render_fn``'s positional arguments other than the medium (the scene; render_scene_indexed's index
            and tables, which take no gradient).
        sigma_t, albedo: the differentiable medium, (3, D, H, W) each; None for a forward-only ``render_fn``.
        group: optional process group.

    Raises:
        ValueError: ``partition`` given (it is set here, from the process group).
        TypeError: a tensor that requires grad among ``args`` while grad mode is on (pass the medium by keyword,
            or its gradient would not be summed over the ranks).

    Example:
        >>> import torch, torch_appearance as ta
        >>> from torch_appearance import distributed
        >>> sigma_t = torch.full((3, 2, 4, 4), 5.0, requires_grad=True)
        >>> albedo = torch.full((3, 2, 4, 4), 0.8)
        >>> distributed.render(ta.render_texels, sigma_t=sigma_t, albedo=albedo, voxel_size=0.1, spp=2).shape
        torch.Size([4, 4, 3])
    """
    for k, a in enumerate(args):
        if isinstance(a, torch.Tensor) and a.requires_grad and torch.is_grad_enabled():
            raise TypeError(f"args: expected the differentiable medium by keyword (sigma_t=, albedo=), got a tensor "
                            f"that requires grad at position {k}")
    if "partition" in kwargs:
        raise ValueError("partition: set by torch_appearance.distributed.render from the process group; do not pass "
                         "it")
    rank, world = rank_and_world(group)
    medium = {name: (x if world == 1 else reduce_gradient(x, group))
              for name, x in (("sigma_t", sigma_t), ("albedo", albedo)) if x is not None}
    if world == 1:
        return render_fn(*args, **medium, **kwargs)
    share = render_fn(*args, **medium, partition=(rank, world), **kwargs)
    return _AllReduceSum.apply(share, group)
