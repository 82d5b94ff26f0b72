"""The processes that train one model together, and the few collectives a training run needs from them.

Replicated data parallelism (docs/architecture.md, "The training loop as a stream of events"): every process holds
the whole model and renders its own training view each step. One all-reduce per step averages the gradients of all
parameters (one flat buffer, the step's loss, PSNR and stop request packed at its end), so every process takes the
same Adam step; MCMC then draws from a generator with the same seed and state, so the copies stay identical without
sending the model. Guards: relocation and growth use rank 0's draw, and a checksum of the parameters is compared
every CHECK_EVERY steps. A run in one process gets `SingleProcess`, whose operations do nothing.
"""

from __future__ import annotations

import contextlib
import os
from datetime import timedelta
from typing import Any, Callable, Iterator, TypeVar

import torch

from ..errors import MCSplatError
from ..gaussians import PARAM_KEYS, GaussianModel
from ..strategy.base import ALONE, Collective

T = TypeVar("T")
CHECK_EVERY = 200  # steps between two comparisons of the processes' parameter checksums


class SingleProcess:
    """One process trains alone."""

    rank = 0
    local_rank = 0
    world_size = 1
    is_main = True
    collective: Collective = ALONE

    def device(self, device: torch.device) -> torch.device:
        return device

    def pick(self, batch: list[int]) -> int:
        return batch[0]

    def on_main(self, action: Callable[[], T]) -> T:
        return action()

    def first_on_each_machine(self, action: Callable[[], Any]) -> None:
        action()

    def check_same_setup(self, setup: dict[str, Any]) -> None:
        pass

    def share_parameters(self, model: GaussianModel) -> None:
        pass

    def reduce_step(self, model: GaussianModel, values: torch.Tensor) -> torch.Tensor:
        return values

    def check_identical(self, model: GaussianModel, step: int) -> None:
        pass

    def gather(self, value: T) -> list[T]:
        return [value]

    def gather_on_main(self, value: T) -> list[T]:
        return [value]

    def close(self, finished: bool) -> None:
        pass


class ProcessGroup:
    """This process in a torch.distributed process group (gloo on the CPU, NCCL on CUDA)."""

    is_main: bool

    def __init__(self, owns_group: bool, timeout: float):
        import torch.distributed as dist

        self._dist = dist
        self.rank, self.world_size = dist.get_rank(), dist.get_world_size()
        self.local_rank = int(os.environ.get("LOCAL_RANK", self.rank))
        self.is_main = self.rank == 0
        self.timeout = timeout
        self._owns_group = owns_group
        if dist.get_backend() == "nccl":  # NCCL's collectives (objects included) run on this process's GPU
            torch.cuda.set_device(self.local_rank)
            self._tensors = torch.device("cuda", self.local_rank)
        else:
            self._tensors = torch.device("cpu")
        self.collective: Collective = _GroupCollective(self)
        self._flat: torch.Tensor | None = None  # the all-reduce buffer, reused while the model keeps its size

    def device(self, device: torch.device) -> torch.device:
        """Each process on a machine takes its own GPU (torchrun's LOCAL_RANK)."""
        return torch.device("cuda", self.local_rank) if device.type == "cuda" else device

    def pick(self, batch: list[int]) -> int:
        """This process's view among the step's `batch` (one shared draw, one view per process)."""
        return batch[self.rank]

    def on_main(self, action: Callable[[], T]) -> T:
        """Run `action` on rank 0 only and hand its result to every process; its error stops every process."""
        outcome: Any = None
        error: BaseException | None = None
        if self.is_main:
            try:
                outcome = ("ok", action())
            except Exception as exc:  # noqa: BLE001 - every process must hear of it, or the others wait forever
                error, outcome = exc, ("error", f"{exc}" if isinstance(exc, MCSplatError) else f"rank 0: {exc!r}")
        box = [outcome]
        with self._talking("set-up"):
            self._dist.broadcast_object_list(box, src=0)
        if error is not None:
            raise error
        status, value = box[0]
        if status == "error":
            raise MCSplatError(value)
        return value

    def first_on_each_machine(self, action: Callable[[], Any]) -> None:
        """`action` on each machine's first process, then on the others (one compile into a shared kernel cache)."""
        if self.local_rank == 0:
            action()
        with self._talking("set-up"):
            self._dist.barrier()
        if self.local_rank != 0:
            action()

    def check_same_setup(self, setup: dict[str, Any]) -> None:
        """Stop every process when one was started with other options or other data than rank 0."""
        everyone = self.gather(setup)
        for rank, theirs in enumerate(everyone):
            for key in sorted(set(setup) | set(theirs)):
                if theirs.get(key) != everyone[0].get(key):
                    raise MCSplatError(f"the training processes were started differently: rank {rank} has {key} = "
                                       f"{_short(theirs.get(key))}, rank 0 has {_short(everyone[0].get(key))}; start "
                                       f"every process with the same options and the same scene")

    def share_parameters(self, model: GaussianModel) -> None:
        """Rank 0's initial parameters on every process (an init from the same seed would do, but machines of
        another kind may round differently)."""
        with self._talking("set-up"):
            for key in PARAM_KEYS:
                data = model.params[key].data
                moved = data.to(self._tensors)
                self._dist.broadcast(moved, src=0)
                data.copy_(moved)

    def reduce_step(self, model: GaussianModel, values: torch.Tensor) -> torch.Tensor:
        """Average every parameter's gradient over the processes with one all-reduce; `values` ([k]: the step's
        loss, PSNR, ...) ride at the end of the same buffer and come back averaged, in their own dtype, on the host.
        The gradients become views of the buffer (no copy back)."""
        params = [model.params[key] for key in PARAM_KEYS]
        for p in params:
            if p.grad is None:
                p.grad = torch.zeros_like(p)
        grads = [p.grad.reshape(-1).to(self._tensors) for p in params]
        tail = values.detach().to(dtype=grads[0].dtype, device=self._tensors)
        size = sum(g.numel() for g in grads) + tail.numel()
        if self._flat is None or self._flat.numel() != size or self._flat.dtype != tail.dtype:
            self._flat = torch.empty(size, dtype=tail.dtype, device=self._tensors)  # kept: fresh pages cost
        flat = torch.cat(grads + [tail], out=self._flat)
        with self._talking("the gradient all-reduce"):
            self._dist.all_reduce(flat)
            flat.mul_(1.0 / self.world_size)
            # On the host: on CUDA the wait for the others happens here, where a failure gets its one-line error.
            averaged = flat[-tail.numel():].to(dtype=values.dtype, device="cpu", copy=True)
        offset = 0
        for p in params:
            count = p.numel()
            p.grad = flat[offset:offset + count].view_as(p).to(p.device)
            offset += count
        return averaged

    def check_identical(self, model: GaussianModel, step: int) -> None:
        """Every CHECK_EVERY steps: compare checksums of the parameters' bits; stop if a copy has diverged."""
        if step % CHECK_EVERY:
            return
        everyone = self.gather(parameter_checksum(model))
        differ = [rank for rank, sums in enumerate(everyone) if sums != everyone[0]]
        if differ:
            raise MCSplatError(f"step {step}: the processes' models are no longer identical (rank(s) "
                               f"{', '.join(map(str, differ))} differ from rank 0), so they no longer train one "
                               f"model; run every process with the same mcsplat and torch versions on the same kind "
                               f"of device, and resume from the last checkpoint")

    def gather(self, value: T) -> list[T]:
        """Every process's `value`, in rank order, on every process."""
        everyone: list[Any] = [None] * self.world_size
        with self._talking("an exchange of results"):
            self._dist.all_gather_object(everyone, value)
        return everyone

    def gather_on_main(self, value: T) -> list[T]:
        """Every process's `value`, in rank order, on rank 0 (the others get an empty list)."""
        everyone: list[Any] | None = [None] * self.world_size if self.is_main else None
        with self._talking("an exchange of results"):
            self._dist.gather_object(value, everyone, dst=0)
        return everyone or []

    def close(self, finished: bool) -> None:
        """Leave the group this process joined. After a finished run, wait for the others first (a process that
        tears its connections down while another still uses them can abort it)."""
        if not (self._owns_group and self._dist.is_initialized()):
            return
        if finished:
            with self._talking("the end of the run"):
                self._dist.barrier()
        self._dist.destroy_process_group()

    @contextlib.contextmanager
    def _talking(self, what: str) -> Iterator[None]:
        """Turns a failed or timed-out collective into one clear error instead of a backend traceback."""
        try:
            yield
        except MCSplatError:
            raise
        except RuntimeError as error:
            first_line = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
            raise MCSplatError(f"rank {self.rank}: lost the other training processes during {what} "
                               f"({first_line[:200]}): one of them stopped (its own error says why) or did not "
                               f"answer within --dist-timeout {self.timeout:g} s") from None


class _GroupCollective:
    """The strategies' view of the process group (strategy.base.Collective)."""

    def __init__(self, group: ProcessGroup):
        self.group = group

    def agree(self, indices: torch.Tensor) -> torch.Tensor:
        dist, device = self.group._dist, self.group._tensors
        with self.group._talking("a relocation"):
            sizes = torch.tensor([indices.numel(), -indices.numel()], dtype=torch.int64, device=device)
            dist.all_reduce(sizes, op=dist.ReduceOp.MAX)
            if int(sizes[0]) != -int(sizes[1]):
                raise MCSplatError("the processes drew different numbers of Gaussians to relocate or grow: their "
                                   "models have diverged; resume from the last checkpoint")
            shared = indices.to(device).contiguous()
            dist.broadcast(shared, src=0)
        return shared.to(indices.device)

    def sum_(self, tensor: torch.Tensor) -> None:
        self._reduce(tensor, self.group._dist.ReduceOp.SUM)

    def max_(self, tensor: torch.Tensor) -> None:
        self._reduce(tensor, self.group._dist.ReduceOp.MAX)

    def _reduce(self, tensor: torch.Tensor, op) -> None:
        moved = tensor.to(self.group._tensors)
        with self.group._talking("a densification"):
            self.group._dist.all_reduce(moved, op=op)
        tensor.copy_(moved)


def parameter_checksum(model: GaussianModel, chunk: int = 1 << 22) -> list[int]:
    """Integers that change when any bit of any parameter does (sums of the raw bits, plain and position-weighted),
    computed where the parameters live, a chunk at a time."""
    sums = [model.num_gaussians]
    for key in PARAM_KEYS:
        data = model.params[key].detach().contiguous().reshape(-1)
        bits = data.view(torch.int32 if data.element_size() == 4 else torch.int64)
        plain = weighted = 0
        for start in range(0, bits.numel(), chunk):
            part = bits[start:start + chunk].to(torch.int64)
            weights = torch.arange(start, start + part.numel(), dtype=torch.int64, device=part.device) % 65_521 + 1
            plain += int(part.sum())
            weighted += int((part * weights).sum())
        sums += [plain, weighted]
    return sums


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 120 else text[:117] + "..."


def join(device_name: str, timeout: float) -> SingleProcess | ProcessGroup:
    """The processes of this run: torchrun's (its environment variables), or the process group the caller has
    initialised (tests, scripts); a process started alone trains alone."""
    import torch.distributed as dist

    if alone():
        return SingleProcess()
    owns_group = not dist.is_initialized()
    if owns_group:
        cuda = device_name == "cuda" or (device_name == "auto" and torch.cuda.is_available())
        if cuda:
            torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
        join_torchrun("nccl" if cuda else "gloo", timedelta(seconds=timeout), "training processes",
                      "torchrun --nproc-per-node 2 -m mcsplat train DATA")
    if dist.get_world_size() == 1:
        if owns_group:
            dist.destroy_process_group()
        return SingleProcess()
    return ProcessGroup(owns_group, timeout)


def alone() -> bool:
    """Whether this process has no others to work with: torch.distributed is missing, or no process group is made
    and torchrun started no other process."""
    import torch.distributed as dist

    if not dist.is_available():
        return True
    return not dist.is_initialized() and int(os.environ.get("WORLD_SIZE", "1")) <= 1


def join_torchrun(backend: str, timeout: timedelta, processes: str, command: str) -> None:
    """Make the process group of torchrun's processes (its environment variables say who they are); when that fails,
    say how to start them (`processes`: what they are called, `command`: an example command line)."""
    import torch.distributed as dist

    try:
        dist.init_process_group(backend=backend, timeout=timeout)
    except (RuntimeError, ValueError) as error:
        raise MCSplatError(f"could not join the other {processes} ({str(error).splitlines()[0]}); start them with "
                           f"torchrun, e.g. `{command}`") from None


def command_for(world_size: int) -> str:
    """The start of the command line that runs `mcsplat` with `world_size` processes again (for the hints that say
    how to resume: a run of N processes continues with N only)."""
    if world_size == 1:
        return "mcsplat"
    per_machine = int(os.environ.get("LOCAL_WORLD_SIZE", world_size))
    machines = max(1, world_size // max(1, per_machine))
    on_machines = f"--nnodes {machines} --rdzv-endpoint HOST:PORT " if machines > 1 else ""
    return f"torchrun {on_machines}--nproc-per-node {per_machine} -m mcsplat"


def threads_per_process() -> int:
    """CPU threads for each of the processes torchrun started on this machine (they share its cores)."""
    local = int(os.environ.get("LOCAL_WORLD_SIZE", os.environ.get("WORLD_SIZE", "1")))
    return max(1, (os.cpu_count() or 1) // max(1, local))
