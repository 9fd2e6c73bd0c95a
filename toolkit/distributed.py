"""Data-parallel training with :mod:`torch.distributed` (launched by ``torchrun``; gloo on CPU, NCCL on CUDA).

One process per rank; every rank holds a full copy of the field and its optimisers, but loads only its own shard of
the training photos (every ``world_size``-th photo, :meth:`Distributed.shard`) and draws its part of the global
batch from it (:meth:`Distributed.local_config`: ``batch_rays / world_size`` rays, the SSIM patches split the same
way). After each backward pass the gradients are averaged over the ranks (:meth:`Distributed.average_gradients`,
an ``all_reduce`` per parameter), so every rank takes the same optimiser step and the copies stay identical bit for
bit; the occupancy grid is broadcast from rank 0 after each update, and the SH light ``l_env`` is a parameter like
any other (the light steps all-reduce its gradient). Decisions that depend on the clock (first checkpoint, the
5-minute checkpoint, snapshots, a ``--minutes`` budget's calibration) are taken by rank 0 and broadcast
(:meth:`Distributed.decide`), so every rank enters the same collectives. Rank 0 alone writes ``config.json``,
``log.jsonl`` and the checkpoints; a checkpoint holds every rank's RNG state, so a resume at the same world size
reproduces the run, and a resume at another world size continues it (the extra ranks get fresh streams).

The per-step all-reduce is a plain loop over the parameters rather than :class:`torch.nn.parallel.DistributedDataParallel`:
a training step calls the field several times (the eikonal term's finite differences, the light step with the field
frozen), which DDP's one-forward-one-backward bucketing does not fit, and gradients that are ``None`` on one rank
(a parameter no ray touched) must be treated alike on all ranks so the optimisers do not drift apart.

Not supported with ``world_size > 1``: per-photo colour correction (``colour_correction``; its gains are indexed by
the local photo) — the run is refused with a message.

Example:
    torchrun --standalone --nproc_per_node 2 -m toolkit.cli train SCENE --out RUN --steps 2000 --threads 1
"""

from __future__ import annotations

import faulthandler
import hashlib
import os
from dataclasses import dataclass, replace
from typing import Any

import torch

from ._checks import ConfigError

__all__ = ["Distributed", "init_from_env", "current", "shutdown", "split_count", "world_size_from_env", "peak_rss_mb"]

_CURRENT: "Distributed | None" = None


def split_count(total: int, rank: int, world_size: int) -> int:
    """The share of ``total`` items that ``rank`` gets when they are dealt out over ``world_size`` ranks (the first
    ``total % world_size`` ranks get one more)."""
    return total // world_size + (1 if rank < total % world_size else 0)


def world_size_from_env() -> int:
    """``WORLD_SIZE`` set by ``torchrun`` (1 when not launched by it)."""
    try:
        return max(1, int(os.environ.get("WORLD_SIZE", "1")))
    except ValueError:
        return 1


@dataclass
class Distributed:
    """This process's place in a data-parallel run (see the module docstring).

    Attributes:
        rank: 0 .. world_size - 1; rank 0 writes the run.
        world_size: number of processes.
        local_rank: index on this node (the CUDA device it uses).
        backend: ``gloo`` or ``nccl``.
    """

    rank: int
    world_size: int
    local_rank: int
    backend: str

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def comm_device(self) -> torch.device:
        """Where tensors must be for the backend's collectives."""
        return torch.device("cuda", torch.cuda.current_device()) if self.backend == "nccl" else torch.device("cpu")

    # ------------------------------------------------------------------------------------------- configuration
    def device_for(self, device: str) -> str:
        """The training device of this rank: ``cuda:LOCAL_RANK`` for ``auto``/``cuda`` with NCCL, else ``device``."""
        if self.backend == "nccl" and device in ("auto", "cuda"):
            return f"cuda:{self.local_rank}"
        return "cpu" if device == "auto" else device

    def local_config(self, cfg):
        """This rank's :class:`~toolkit.train.TrainConfig`: its part of the global batch and of the SSIM patches,
        and its device. The run's ``config.json`` keeps the global values."""
        if cfg.batch_rays < 16 * self.world_size:
            raise ConfigError(f"batch_rays={cfg.batch_rays} is too small for {self.world_size} processes: each rank "
                              f"needs at least 16 rays (give --batch-rays ≥ {16 * self.world_size})")
        rays = split_count(cfg.batch_rays, self.rank, self.world_size)
        s = cfg.ssim_patch_size  # patches never take the whole local batch (a tiny batch may drop some)
        patches = min(split_count(cfg.ssim_patches, self.rank, self.world_size), (rays - 1) // (s * s))
        return replace(cfg, batch_rays=rays, ssim_patches=patches, device=self.device_for(cfg.device))

    def shard(self, scene):
        """This rank's photos: every ``world_size``-th one from ``rank`` (each shard spans the whole capture).

        Raises:
            ConfigError: fewer photos than processes.
        """
        if len(scene) < self.world_size:
            raise ConfigError(f"the scene has {len(scene)} training photos, fewer than the {self.world_size} "
                              "processes: every rank needs at least one (use fewer processes)")
        return scene.subset(list(range(self.rank, len(scene), self.world_size)))

    def check_supported(self, cfg, data) -> None:
        """Refuse settings data-parallel training does not handle (see the module docstring)."""
        if cfg.colour_correction == "on" or (cfg.colour_correction == "auto" and data.colour_init is not None):
            raise ConfigError("per-photo colour correction (a colour prior in priors/colour/, or colour_correction=on) "
                              f"is not supported with {self.world_size} processes yet: train with one process, or "
                              "move the colour prior aside")

    # ------------------------------------------------------------------------------------------- collectives
    def barrier(self) -> None:
        torch.distributed.barrier()

    def broadcast_object(self, obj: Any) -> Any:
        """Rank 0's ``obj`` on every rank."""
        box = [obj if self.is_main else None]
        torch.distributed.broadcast_object_list(box, src=0)
        return box[0]

    def gather_objects(self, obj: Any) -> list:
        """Every rank's ``obj``, in rank order, on every rank."""
        out: list = [None] * self.world_size
        torch.distributed.all_gather_object(out, obj)
        return out

    def decide(self, *flags: bool) -> list[bool]:
        """Rank 0's ``flags`` on every rank (decisions that depend on the clock, so every rank acts alike)."""
        t = torch.tensor([1 if f else 0 for f in flags], dtype=torch.int32, device=self.comm_device)
        torch.distributed.broadcast(t, src=0)
        return [bool(v) for v in t.tolist()]

    def _broadcast_tensor(self, t: torch.Tensor) -> None:
        buf = t.detach().to(self.comm_device)
        torch.distributed.broadcast(buf, src=0)
        if buf is not t:
            with torch.no_grad():
                t.copy_(buf.to(t.device))

    def broadcast_state(self, state) -> None:
        """Make every rank start from rank 0's state: field, background, light (their initial values depend on the
        rank's photos: the border colour, the grey ambient) and the occupancy grid."""
        modules = [state.field, state.background] + ([state.colour] if state.colour is not None else [])
        for m in modules:
            for t in list(m.parameters()) + list(m.buffers()):
                self._broadcast_tensor(t.data)
        self._broadcast_tensor(state.l_env.data)
        self.sync_occupancy(state.occupancy)

    def sync_occupancy(self, occupancy) -> None:
        """Rank 0's occupancy grid on every rank (after an update, which samples cells at random per rank)."""
        self._broadcast_tensor(occupancy.density)
        mask = occupancy.mask.to(torch.uint8)
        self._broadcast_tensor(mask)
        occupancy.mask = mask.bool().to(occupancy.mask.device)

    def average_gradients(self, optimizer: torch.optim.Optimizer) -> None:
        """Average the gradients of ``optimizer``'s parameters over the ranks (in place). A parameter without a
        gradient on some rank counts as a zero gradient there; it keeps ``None`` only where no rank has one, so the
        optimisers of all ranks see the same gradients and stay identical."""
        params = [p for g in optimizer.param_groups for p in g["params"]]
        if not params:
            return
        dev = self.comm_device
        has = torch.tensor([p.grad is not None for p in params], dtype=torch.int32, device=dev)
        torch.distributed.all_reduce(has, op=torch.distributed.ReduceOp.MAX)
        for p, h in zip(params, has.tolist()):
            if not h:
                continue
            if p.grad is None:
                p.grad = torch.zeros_like(p)
            g = p.grad.to(dev)
            torch.distributed.all_reduce(g)
            g.div_(self.world_size)
            if g is not p.grad:
                p.grad.copy_(g.to(p.grad.device))

    def average_scalars(self, values: dict, keys: tuple[str, ...]) -> dict:
        """``values`` with the numbers under ``keys`` averaged over the ranks (every rank must have the keys)."""
        keys = tuple(k for k in keys if k in values)
        if not keys:
            return values
        t = torch.tensor([float(values[k]) for k in keys], dtype=torch.float64, device=self.comm_device)
        torch.distributed.all_reduce(t)
        out = dict(values)
        out.update({k: float(v) / self.world_size for k, v in zip(keys, t.tolist())})
        return out

    def parameter_digests(self, state) -> list[str]:
        """A digest of each rank's parameters (field, background, light), in rank order: equal when in sync."""
        h = hashlib.sha1()
        for m in (state.field, state.background):
            for name, t in m.state_dict().items():
                h.update(name.encode())
                h.update(t.detach().cpu().contiguous().numpy().tobytes())
        h.update(state.l_env.detach().cpu().contiguous().numpy().tobytes())
        return self.gather_objects(h.hexdigest()[:16])

    # ------------------------------------------------------------------------------------------- random streams
    def seed_generator(self, state) -> None:
        """Give rank ``r > 0`` its own ray stream (rank 0 keeps the single-process one)."""
        if self.rank:
            state.generator.manual_seed(rank_seed(state.cfg.seed, self.rank, state.step))

    def restore_generator(self, state, checkpoint: dict) -> None:
        """After a resume: this rank's saved RNG state when the run was saved at this world size, else a fresh
        stream for ranks the saved run did not have."""
        saved = checkpoint.get("generators")
        if saved is not None and len(saved) == self.world_size:
            state.generator.set_state(saved[self.rank])
        elif self.rank:
            state.generator.manual_seed(rank_seed(state.cfg.seed, self.rank, state.step))


def peak_rss_mb() -> float:
    """This process's peak resident memory in MB (Linux ``ru_maxrss``; 0 where ``resource`` is missing)."""
    try:
        import resource
    except ImportError:
        return 0.0
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1)


def rank_seed(seed: int, rank: int, step: int) -> int:
    """The seed of rank ``rank``'s ray stream from step ``step`` (distinct per rank and per resume point)."""
    return (int(seed) * 1_000_003 + rank * 7919 + step * 104_729 + 1) % (2 ** 63)


def init_from_env(device: str = "auto") -> Distributed | None:
    """Join the process group ``torchrun`` set up (``WORLD_SIZE`` > 1 in the environment); None for a single process.

    The backend is NCCL when CUDA is used (``device`` auto or cuda and a GPU present), else gloo.
    """
    global _CURRENT
    if _CURRENT is not None:
        return _CURRENT
    world = world_size_from_env()
    if world <= 1:
        return None
    import torch.distributed as dist

    for var in ("RANK", "MASTER_ADDR", "MASTER_PORT"):
        if var not in os.environ:
            raise ConfigError(f"WORLD_SIZE={world} but {var} is not set: launch data-parallel training with torchrun "
                              "(`torchrun --standalone --nproc_per_node N -m toolkit.cli train ...`)")
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    try:  # a rank killed by a signal (a C++ abort in a collective) prints where it was
        faulthandler.enable()
    except (OSError, ValueError, AttributeError):  # stderr is not a file (captured): no stacks, nothing else lost
        pass
    use_cuda = device != "cpu" and torch.cuda.is_available() and not device.startswith("cpu")
    backend = "nccl" if use_cuda else "gloo"
    if use_cuda:
        torch.cuda.set_device(local_rank)
    if not dist.is_initialized():
        dist.init_process_group(backend=backend)
    _CURRENT = Distributed(rank=dist.get_rank(), world_size=dist.get_world_size(), local_rank=local_rank,
                           backend=backend)
    return _CURRENT


def current() -> Distributed | None:
    """The data-parallel context of this process (None: a single-process run)."""
    return _CURRENT


def shutdown(finished: bool = False) -> None:
    """Leave the process group (end of a data-parallel command).

    ``finished``: every rank reached the end of the command normally, so they meet at a barrier first and tear their
    connections down together (a rank that left while rank 0 still wrote the run would close its side of live
    connections). After an error the other ranks may be inside another collective, so there is no barrier then.
    """
    global _CURRENT
    ddp, _CURRENT = _CURRENT, None
    if ddp is not None and torch.distributed.is_initialized():
        try:
            if finished:
                torch.distributed.barrier()
        finally:
            torch.distributed.destroy_process_group()
