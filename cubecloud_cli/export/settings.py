"""Everything that decides what `export` writes (recorded in its manifest)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import ClassVar, Literal, get_args

from cubecloud_cli.cameras import OrbitSpec, PinholeCameras, orbit_cameras, sphere_cameras, stack_cameras, stack_offsets
from cubecloud_cli.cameras.novel import DEFAULT_DIRECTIONS, NovelViewSet
from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.presets import preset_default
from cubecloud_cli.render.image_model_names import IMAGE_MODELS
from cubecloud_cli.transfer.tissue_presets import DEFAULT_TRANSFER, TRANSFER_PRESETS

RenderSource = Literal["grid", "field"]
RENDER_SOURCES = get_args(RenderSource)
# sphere and orbit: docs/design.md §2. stack: the paper's 3DGS baseline, parallel slices seen from one pose.
CameraPath = Literal["sphere", "orbit", "stack"]
CAMERA_PATHS = get_args(CameraPath)
CAMERA_BUILDERS = {"sphere": sphere_cameras, "orbit": orbit_cameras, "stack": stack_cameras}
MAX_NOVEL_DIRECTIONS = 256
MAX_TRANSFER_SET = 64
MAX_HELD_OUT_WINDOWS = 64
MAX_RESOLUTION = 16384  # beyond this a single view no longer fits a float32 tensor of pixels × steps
# A resolution the preset leaves to the volume: views as wide as the volume, up to this.
RESOLUTION_FROM_VOLUME = "volume"
MAX_VOLUME_RESOLUTION = 512


@dataclass(frozen=True)
class ExportSettings:
    STAGE: ClassVar[str] = "export"

    # The point cloud (paper Eq. 1–2).
    cube: int = 16
    """Cube side in voxels for point sampling (the paper: 16)."""
    points_per_cube: int = preset_default("export", "points_per_cube")
    """Points drawn uniformly in each cube."""
    max_points: int = preset_default("export", "max_points")  # 0: keep every non-air point
    """Point budget, filled where the field has structure (edges) first; 0 keeps every non-air point."""
    air_threshold: float = 0.02
    """Points whose CuNeRF intensity is at or below this are air and dropped."""
    # The training cameras (docs/design.md §2): over the sphere, on a ring about ``axis``, or the paper
    # baseline's stack of slices across ``axis``.
    cameras: CameraPath = preset_default("export", "cameras")
    """sphere: --views cameras spread evenly over the whole sphere of directions, --axis up. orbit: --views cameras
    on a ring around --axis (the paper's). stack: the paper's 3DGS baseline, --views parallel slices across
    --axis (lr: sagittal) all seen from one camera pose; needs --view slice."""
    views: int = preset_default("export", "views")
    """Training cameras (the paper: 60); every 8th is held out for testing."""
    axis: str = preset_default("export", "axis")
    """Orbit axis, or the sphere's pole axis and image up: si (long axis, head up), ap (the paper's sagittal axis),
    lr. With --cameras stack, the slice normal instead: lr sagittal (its default), ap coronal, si axial."""
    radius: float = 4.0
    """Camera distance from the volume's centre, in world units (the volume spans -1..1)."""
    fov: float | None = None
    """Field of view in degrees (default: just wide enough for the whole volume in every view)."""
    resolution: int | str = preset_default("export", "resolution")
    """Image width and height in pixels; the detail preset's "volume" is the volume's side, up to 512."""
    elevation: float = 0.0
    """--cameras orbit: degrees the orbit is raised out of its plane (all views alike)."""
    # The images (docs/design.md §3).
    view: str = preset_default("export", "view")
    """Image model: dvr (volume rendering through a transfer function), slice (the cross-section facing the camera,
    the paper's images) or mip (maximum intensity)."""
    transfer: str = DEFAULT_TRANSFER
    """dvr transfer function preset, in HU for CT."""
    tf_low: float | None = None
    """dvr: intensity (0..1) where tissue starts to absorb; overrides the preset."""
    tf_high: float | None = None
    """dvr: intensity (0..1) of full absorption; overrides the preset."""
    tf_density: float | None = None
    """dvr: extinction per world unit at full absorption; higher is more opaque."""
    transfer_set: int = 1
    """dvr: render the training views under this many transfer functions: --transfer first, then the presets eval
    does not hold out, then half the rest as bands tiling the value range evenly, then seeded random bands and ramps
    by turns. A `splat --scalar` run trains under all of them, so that it shows other tissue without retraining; each
    one more costs a render of every training view, or of one in --transfer-stride. 41 at a stride of 6 scored best
    on transfer functions held out of training: 7.7 renders of every view, against 5 for 5 at every view
    (docs/results.md, "Scalar scenes")."""
    transfer_stride: int = 1
    """dvr with --transfer-set: render each transfer function after the export's own at every N-th view only, each
    from an offset of its own, so that a set N times as large costs the same renders (the export's own is rendered
    at every view). splat --scalar draws among the images rendered."""
    held_out_windows: int = 0
    """dvr with --transfer-set > 1: also hold out this many seeded random bands and ramps, which eval scores the scalar
    run under beside bone, lung, vessels and one random ramp: a wider measure of transfer functions never trained on.
    Each costs a render of the novel views at 0.75–1.33×."""
    step: float = 1.0  # voxels of the preprocessed volume between ray samples
    """Ray-march step in voxels of the preprocessed volume."""
    render_from: RenderSource = "grid"
    """grid: bake CuNeRF to a grid once, then render (fast). field: query CuNeRF's cube renders at every ray sample
    (slow; exact)."""
    bake_size: int | None = None  # None: the preprocessed volume's size
    """Grid side for --render-from grid (default: the volume's size)."""
    seed: int = 0
    """Seed of the point sampling, of the random members of --transfer-set and of the random ramps and windows eval
    holds out (bone, lung and vessels do not change with it)."""
    # The novel-view test (docs/design.md §2): directions, each at every magnification; 0 for none.
    novel_directions: int = DEFAULT_DIRECTIONS
    """Directions of the novel-view test (from the head, from the feet, then fixed random ones), each rendered from
    the volume at magnifications 0.5, 0.75, 1, 1.33 and 2 with pixel-area references; eval scores every run on
    them. 0 for none."""

    def for_volume(self, volume_size: int) -> "ExportSettings":
        """These settings with a resolution left to the volume made concrete."""
        if self.resolution != RESOLUTION_FROM_VOLUME:
            return self
        return replace(self, resolution=min(volume_size, MAX_VOLUME_RESOLUTION))

    def pixels(self) -> int:
        """Image width and height (a resolution left to the volume must be made concrete first)."""
        if not isinstance(self.resolution, int):
            raise ValueError(f"resolution {self.resolution!r} depends on the volume: call for_volume first")
        return self.resolution

    def orbit(self) -> OrbitSpec:
        return OrbitSpec(self.views, self.axis, self.radius, self.pixels(), self.elevation, self.fov)

    def camera_set(self) -> PinholeCameras:
        return CAMERA_BUILDERS[self.cameras](self.orbit())

    def novel_view_set(self) -> NovelViewSet:
        return NovelViewSet.build(self.novel_directions, self.radius, self.pixels())

    def slice_offsets(self) -> tuple[float, ...]:
        """Per-view slice planes: across the volume for a stack, through the origin otherwise."""
        return tuple(float(d) for d in stack_offsets(self.views)) if self.cameras == "stack" else ()

    def validate(self) -> None:
        """Refuse options that no volume makes right, with a one-line error naming the fix."""
        if isinstance(self.resolution, str) and self.resolution != RESOLUTION_FROM_VOLUME:
            raise CubecloudError(f"--resolution {self.resolution!r} must be a number of pixels, e.g. 256")
        self.for_volume(MAX_VOLUME_RESOLUTION).orbit().validate()
        if self.cameras not in CAMERA_PATHS:
            raise CubecloudError(f"--cameras {self.cameras!r} must be one of {', '.join(CAMERA_PATHS)}")
        if self.cameras == "stack" and self.view != "slice":
            raise CubecloudError(
                f"--cameras stack shows parallel slices from one pose and needs --view slice (got --view {self.view})"
            )
        if self.cameras != "orbit" and self.elevation != 0.0:
            raise CubecloudError(
                f"--elevation tilts the orbit and has no meaning with --cameras {self.cameras}: leave it out, or use --cameras orbit"
            )
        if not 0 <= self.novel_directions <= MAX_NOVEL_DIRECTIONS:
            raise CubecloudError(
                f"--novel-directions {self.novel_directions} must be within 0..{MAX_NOVEL_DIRECTIONS} (0: no novel-view test)"
            )
        if self.for_volume(MAX_VOLUME_RESOLUTION).pixels() > MAX_RESOLUTION:
            raise CubecloudError(
                f"--resolution {self.resolution} is beyond {MAX_RESOLUTION} pixels: choose e.g. 256 or 512"
            )
        if self.cube < 1:
            raise CubecloudError(f"--cube {self.cube} must be at least 1 voxel (the paper uses 16)")
        if self.points_per_cube < 1:
            raise CubecloudError(f"--points-per-cube {self.points_per_cube} must be at least 1")
        if self.max_points < 0:
            raise CubecloudError(f"--max-points {self.max_points} must be 0 (no budget) or more")
        if not 0.0 <= self.air_threshold < 1.0:
            raise CubecloudError(f"--air-threshold {self.air_threshold:g} must be within [0, 1)")
        if self.view not in IMAGE_MODELS:
            raise CubecloudError(f"--view {self.view!r} must be one of {', '.join(IMAGE_MODELS)}")
        if self.transfer not in TRANSFER_PRESETS:
            raise CubecloudError(f"--transfer {self.transfer!r} must be one of {', '.join(TRANSFER_PRESETS)}")
        if not 1 <= self.transfer_set <= MAX_TRANSFER_SET:
            raise CubecloudError(f"--transfer-set {self.transfer_set} must be within 1..{MAX_TRANSFER_SET}")
        if self.transfer_set > 1 and self.view != "dvr":
            raise CubecloudError(
                f"--transfer-set renders through transfer functions, which only --view dvr has (got --view {self.view})"
            )
        if not 0 <= self.held_out_windows <= MAX_HELD_OUT_WINDOWS:
            raise CubecloudError(f"--held-out-windows {self.held_out_windows} must be within 0..{MAX_HELD_OUT_WINDOWS}")
        if not 1 <= self.transfer_stride <= self.views:
            raise CubecloudError(
                f"--transfer-stride {self.transfer_stride} must be within 1..{self.views} (the views): 1 renders "
                "every view under every transfer function"
            )
        if self.transfer_stride > 1 and self.transfer_set < 2:
            raise CubecloudError(
                "--transfer-stride spreads a set of transfer functions over the views: it needs --transfer-set 2 or "
                "more (e.g. 41 with --transfer-stride 6)"
            )
        if self.held_out_windows and (self.transfer_set < 2 or self.novel_directions == 0):
            raise CubecloudError(
                "--held-out-windows scores a scalar scene at the novel views: it needs --transfer-set 2 or more "
                "(e.g. 5) and --novel-directions 1 or more"
            )
        if not (0.05 <= self.step <= 8.0):
            raise CubecloudError(f"--step {self.step:g} must be within 0.05..8 voxels (1 is the usual choice)")
        if self.render_from not in RENDER_SOURCES:
            raise CubecloudError(f"--render-from {self.render_from!r} must be grid or field")
        if self.bake_size is not None and not 2 <= self.bake_size <= 1024:
            raise CubecloudError(f"--bake-size {self.bake_size} must be within 2..1024 voxels")

    def check_for_volume(self, volume_size: int) -> None:
        """Refuse options that do not fit a volume of ``volume_size``³ voxels."""
        if self.step >= volume_size:
            raise CubecloudError(
                f"--step {self.step:g} spans the whole {volume_size}³ volume: choose a smaller step, e.g. 1"
            )
        if self.cube > volume_size:
            raise CubecloudError(
                f"--cube {self.cube} is larger than the {volume_size}³ volume: choose at most {volume_size}"
            )

    def bake_resolution(self, volume_size: int) -> int:
        return self.bake_size or volume_size

    def as_dict(self) -> dict:
        return asdict(self)
