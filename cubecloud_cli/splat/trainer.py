"""The 3DGS training loop: one view per iteration, the paper's loss, Adam per parameter group, the
density-control strategy it is given (``densify.py``), checkpoints that resume exactly."""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import torch

from cubecloud_cli.cameras import PinholeCameras
from cubecloud_cli.core.writes import write_atomically
from cubecloud_cli.numerics.adam import adam
from cubecloud_cli.numerics.metrics import psnr_from_mse
from cubecloud_cli.numerics.readback import GroupedReads
from cubecloud_cli.raster.backends import NUMBA, Rasterized, Rasterizer, rasterizer_for
from cubecloud_cli.raster.cpu.backward_compile import BackwardCompile
from cubecloud_cli.splat.densify import DensityStrategy, Trainable
from cubecloud_cli.splat.losses import photometric_loss, value_anchor_loss, volume_at
from cubecloud_cli.splat.scalar_gaussians import GaussianModel
from cubecloud_cli.splat.settings import SplatSettings
from cubecloud_cli.splat.smoothing import RECOMPUTE_EVERY, filter_variances
from cubecloud_cli.splat.training_views import TrainingScene
from cubecloud_cli.splat.value_spread import scan_gradient_at, value_spread_loss
from cubecloud_cli.transfer.training_set import member_slot

# A scalar scene reads the scan at its centres this often (and whenever the Gaussians change).
SCAN_REREAD_EVERY = 10


def render_camera(
    gaussians: GaussianModel,
    cameras: PinholeCameras,
    view: int,
    sh_degree: int,
    rasterizer: Rasterizer,
    retain: bool = False,
    antialias: bool = False,
) -> Rasterized:
    """Render ``gaussians`` from camera ``view`` of ``cameras`` (any orbit, not only the scene's);
    ``antialias``: through the 2D Mip filter (the 3D filter, if any, is part of ``gaussians``)."""
    device = gaussians.means.device
    rotation = torch.as_tensor(cameras.rotations[view], dtype=torch.float32, device=device)
    translation = torch.as_tensor(cameras.translations[view], dtype=torch.float32, device=device)
    centre = torch.as_tensor(cameras.centres()[view], dtype=torch.float32, device=device)
    scales, opacities, colours = gaussians.drawn(centre, sh_degree)
    return rasterizer.render(
        gaussians.means,
        scales,
        gaussians.quaternions,
        opacities,
        colours,
        rotation,
        translation,
        float(cameras.focal),
        cameras.width,
        cameras.height,
        retain_screen_grad=retain,
        antialias=antialias,
    )


def render(
    gaussians: GaussianModel,
    scene: TrainingScene,
    view: int,
    sh_degree: int,
    rasterizer: Rasterizer,
    retain: bool = False,
    antialias: bool = False,
) -> Rasterized:
    return render_camera(gaussians, scene.cameras, view, sh_degree, rasterizer, retain, antialias)


class SplatTrainer:
    """Trains ``gaussians`` on ``scene``; ``strategy`` decides how their set changes
    (``densify.strategy_for(settings, scene.extent)`` gives the one the settings ask for)."""

    def __init__(
        self,
        gaussians: GaussianModel,
        scene: TrainingScene,
        settings: SplatSettings,
        device: torch.device,
        strategy: DensityStrategy,
    ):
        self.settings = settings
        # A scalar model's values are held to this volume ([x, y, z] over the cube) with weight
        # settings.value_anchor, and its Gaussians thin across the volume's edges with weight
        # settings.value_spread; the stage sets it for --scalar runs (None: held to nothing).
        self.scan_values: torch.Tensor | None = None
        # Kept between reads (_scan_at_centres) and in checkpoints, so that a resumed run holds its
        # values to what an uninterrupted one would.
        self._scan_at_centres_read: torch.Tensor | None = None
        self._scan_gradient_read: torch.Tensor | None = None
        self.scene = scene
        self.device = device
        self.rasterizer = rasterizer_for(device)
        self.extent = scene.extent
        for name in gaussians.TRAINED:
            setattr(gaussians, name, getattr(gaussians, name).detach().to(device).requires_grad_(True))
        self.gaussians = gaussians
        # What training started from; a restored checkpoint replaces the Gaussians, not this.
        self.initial_count = len(gaussians)
        rates = {
            "means": settings.lr_means * self.extent,
            "log_scales": settings.lr_scales,
            "quaternions": settings.lr_rotation,
            "opacity_logits": settings.lr_opacity,
            "sh_dc": settings.lr_sh,
            "sh_rest": settings.lr_sh / 20.0,
            "value_logits": settings.lr_value,
            "log_lengths": settings.lr_length,
        }
        groups = [{"params": [getattr(gaussians, name)], "lr": rates[name], "name": name} for name in gaussians.TRAINED]
        # Fused: one pass over each parameter instead of about ten elementwise ops, each with its
        # own temporary; on the CPU a 75k-Gaussian step took 3.5 ms and takes 0.9 ms on one thread.
        self.optimizer = adam(groups, eps=1e-15)
        self.strategy = strategy
        self.strategy.initialize(len(gaussians), device)
        self.schedule = settings.schedule()
        self.generator = torch.Generator().manual_seed(settings.seed)
        self.iteration = 0
        self._stepped = False
        self.elapsed_s = 0.0
        # Each step's loss and whether its parameters are finite, read back in groups on a GPU.
        self._reads = GroupedReads.for_device(device)
        self.last_loss: float | None = None  # the loss of the last step read back
        self.history: list[dict] = []
        self._queue: list[int] = []
        self.images = scene.images.to(device)
        # A scalar scene trained under several transfer functions: each step draws one.
        self.transfer_images = None if scene.transfer_images is None else scene.transfer_images.to(device)
        self._transfer_pairs = scene.transfer_pairs() if scene.transfer_images is not None else []
        self.identity: dict | None = None  # the scene, as the stage describes it in checkpoints
        self.training_cameras = scene.cameras.subset(scene.train)
        self._update_smoothing()

    def _update_smoothing(self) -> None:
        """The 3D filter for the Gaussians as they are now (Mip-Splatting's, from the training views)."""
        if self.settings.antialias:
            self.gaussians.smoothing = filter_variances(
                self.gaussians.means.detach(), self.training_cameras, self.settings.filter_scale
            )

    def render(self, view: int, retain: bool = False) -> Rasterized:
        return render_camera(
            self.gaussians, self.scene.cameras, view, self.sh_degree, self.rasterizer, retain, self.settings.antialias
        )

    # -- one iteration --------------------------------------------------------------------

    def next_view(self) -> int:
        if not self._queue:
            order = torch.randperm(len(self.scene.train), generator=self.generator).tolist()
            self._queue = [self.scene.train[i] for i in order]
        return self._queue.pop()

    @property
    def sh_degree(self) -> int:
        return min(self.settings.sh_degree, self.iteration // self.schedule["sh_up_every"])

    def means_lr(self) -> float:
        t = min(1.0, self.iteration / max(1, self.settings.iterations))
        start, end = self.settings.lr_means * self.extent, self.settings.lr_means_final * self.extent
        return math.exp((1 - t) * math.log(start) + t * math.log(end))

    def loss(self, image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """A step's loss: the photometric loss, plus in a scalar scene the value anchor and the
        scan's spread over each Gaussian (``value_spread.py``)."""
        loss = photometric_loss(image, target, self.settings.dssim_weight, self.settings.rmse_share)
        if self.scan_values is not None:
            scan, gradient = self._scan_at_centres()
            if self.settings.value_anchor > 0:
                loss = loss + self.settings.value_anchor * value_anchor_loss(self.gaussians.values(), scan)
            if gradient is not None:
                g = self.gaussians
                loss = loss + self.settings.value_spread * value_spread_loss(g.quaternions, g.log_scales, gradient)
        return loss

    def step(self) -> float:
        started = time.perf_counter()
        view = self.next_view()
        for group in self.optimizer.param_groups:
            if group["name"] == "means":
                group["lr"] = self.means_lr()
        # A trainer's first step compiles the rasterizer's backward on the other core (unless
        # this process has it already); later steps need not ask.
        backward_compile = None
        if not self._stepped and self.rasterizer is NUMBA:
            backward_compile = BackwardCompile.start()
        self._stepped = True
        view, target = self._target(view)
        rendered = self.render(view, retain=True)
        loss = self.loss(rendered.image, target)
        if backward_compile is not None:
            backward_compile.before_backward()
        loss.backward()
        self.iteration += 1
        refining = self.strategy.gathers_statistics(self.iteration)
        self.strategy.step_post_backward(self.iteration, rendered, self.scene.cameras.width, self.scene.cameras.height)
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        # One sum per parameter: NaN and ±Inf propagate into it, at a fraction of isfinite's cost.
        sums = torch.stack([getattr(self.gaussians, name).detach().sum() for name in self.gaussians.TRAINED])
        finite = torch.isfinite(sums).all().to(loss.dtype)
        due = self._reads.push(self.iteration, torch.stack((loss.detach(), finite)))
        if due or self.strategy.changes_at(self.iteration):
            # The set of Gaussians changes only once its values are known finite; the step's own
            # clock counts this wait (read_back would count it twice).
            self._check(self._reads.read())
        if self.strategy.step_post_optimizer(self.iteration, Trainable(self.gaussians, self.optimizer, self.generator)):
            self._update_smoothing()  # for the Gaussians added and removed
            self._scan_at_centres_read = self._scan_gradient_read = None
        if not refining and self.iteration % RECOMPUTE_EVERY == 0:
            self._update_smoothing()  # the means still move a little once densification stops
        self.elapsed_s += time.perf_counter() - started
        return loss.detach()

    def _scan_at_centres(self) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The scan's value at each Gaussian's centre, and its gradient there with --value-spread,
        read again once the Gaussians change and every SCAN_REREAD_EVERY steps: in that many steps
        a centre moves a fraction of a voxel, and reading 50,000 scattered centres took 3 ms of a
        25 ms step on a CPU."""
        if self._scan_at_centres_read is None or self.iteration % SCAN_REREAD_EVERY == 0:
            with torch.no_grad():
                means = self.gaussians.means.detach()
                self._scan_at_centres_read = volume_at(self.scan_values, means)
                spread = self.settings.value_spread > 0
                self._scan_gradient_read = scan_gradient_at(self.scan_values, means) if spread else None
        return self._scan_at_centres_read, self._scan_gradient_read

    def _target(self, view: int) -> tuple[int, torch.Tensor]:
        """This step's view and its image: ``view`` under the scene's transfer function, or an image
        drawn from its set (the Gaussians are drawn under its transfer function until the next draw).
        With every member at every view a member is drawn for ``view``; with a strided set, one of
        the images rendered, the export's own at ``view`` among them."""
        if self.transfer_images is None:
            return view, self.images[view]
        if self.scene.transfer_stride == 1:
            index = int(torch.randint(len(self.scene.transfers), (1,), generator=self.generator))
            self.gaussians.transfer = self.scene.transfers[index]
            return view, self.transfer_images[index, view]
        pick = int(torch.randint(len(self.scene.train) + len(self._transfer_pairs), (1,), generator=self.generator))
        index = 0
        if pick >= len(self.scene.train):
            index, view = self._transfer_pairs[pick - len(self.scene.train)]
        self.gaussians.transfer = self.scene.transfers[index]
        if index == 0:
            return view, self.images[view]
        return view, self.transfer_images[index, member_slot(index, view, self.scene.transfer_stride)]

    def draw_under_first_transfer(self) -> None:
        """Draw the Gaussians under the scene's own transfer function (that of ``images``), as
        evaluation, the preview and the PLY's reference columns do."""
        if self.transfer_images is not None:
            self.gaussians.transfer = self.scene.transfers[0]

    def read_back(self) -> None:
        """Read the steps' values not yet read: raise at the first step whose parameters or loss
        are not finite, else keep the last loss. The wait for the device counts as training time."""
        started = time.perf_counter()
        read = self._reads.read()
        self.elapsed_s += time.perf_counter() - started
        self._check(read)

    def _check(self, read: list[tuple[int, list[float]]]) -> None:
        for iteration, (loss, finite) in read:
            if finite < 1.0:
                raise FloatingPointError(f"a Gaussian parameter became NaN or Inf at iteration {iteration}")
            if not math.isfinite(loss):
                raise FloatingPointError(f"the loss is {loss} at iteration {iteration}")
            self.last_loss = loss

    # -- evaluation and checkpoints -------------------------------------------------------

    @torch.no_grad()
    def evaluate(self, views: list[int]) -> dict[str, float]:
        """Mean PSNR (per view, then averaged) and L1 on ``views``."""
        if not views:
            return {}
        self.draw_under_first_transfer()
        scores, errors = [], []
        for view in views:
            image = self.render(view).image.clamp(0.0, 1.0)
            target = self.images[view]
            scores.append(psnr_from_mse(float(((image - target) ** 2).mean())))
            errors.append(float((image - target).abs().mean()))
        return {"psnr": float(np.mean(scores)), "l1": float(np.mean(errors))}

    def state(self) -> dict:
        self.read_back()  # a checkpoint never holds Gaussians past a step that was not finite
        return {
            "iteration": self.iteration,
            "elapsed_s": self.elapsed_s,
            "history": self.history,
            "gaussians": {name: getattr(self.gaussians, name).detach().cpu() for name in self.gaussians.TRAINED},
            "smoothing": None if self.gaussians.smoothing is None else self.gaussians.smoothing.cpu(),
            "scan_at_centres": None if self._scan_at_centres_read is None else self._scan_at_centres_read.cpu(),
            "scan_gradient_at_centres": None if self._scan_gradient_read is None else self._scan_gradient_read.cpu(),
            "optimizer": self.optimizer.state_dict(),
            **self.strategy.state_dict(),
            "generator": self.generator.get_state(),
            "queue": list(self._queue),
            "settings": self.settings.as_dict(),
            "scene": self.identity,
        }

    def save(self, path: Path) -> None:
        state = self.state()
        write_atomically(Path(path), lambda temporary: torch.save(state, temporary))

    def restore(self, state: dict) -> None:
        for group in self.optimizer.param_groups:
            name = group["name"]
            value = state["gaussians"][name].to(self.device).requires_grad_(True)
            group["params"][0] = value
            setattr(self.gaussians, name, value)
        smoothing = state.get("smoothing")
        self.gaussians.smoothing = None if smoothing is None else smoothing.to(self.device)
        scan = state.get("scan_at_centres")  # a checkpoint from before it was kept reads the scan again
        gradient = state.get("scan_gradient_at_centres")
        if scan is None or (gradient is None and self.settings.value_spread > 0):
            scan = gradient = None
        self._scan_at_centres_read = None if scan is None else scan.to(self.device)
        self._scan_gradient_read = None if gradient is None else gradient.to(self.device)
        self.optimizer.state.clear()
        self.optimizer.load_state_dict(state["optimizer"])
        self.strategy.load_state_dict(state, len(self.gaussians), self.device)
        self.generator.set_state(state["generator"])
        self._queue = list(state["queue"])
        self.iteration = int(state["iteration"])
        self.elapsed_s = float(state["elapsed_s"])
        self.history = list(state["history"])
