"""The built-in 4D patient: a generated child's torso that breathes through a voiding cystourethrogram.

`builtin_phases("child-torso", cache_dir)` gives the phases as (time_s, loader) pairs. The
first call builds every phase (5-15 s on a busy 2-core machine) and writes it to
`cache_dir` as MetaImage (.mha, zlib-compressed; any CT viewer opens it); later calls only
read the manifest. The cache folder's name carries a key made of GENERATOR_VERSION, the
timeline and grid parameters and a digest of the generator's source, so a changed
generator rebuilds.

Timeline (32 phases, one every second; SEQUENCE_S = 32 s, then the case loops): the
voiding cystourethrogram goes through eight stages (STAGES: drained with the catheter in,
filling, full, voiding with the urethra distended, residual), each held for one 4 s
breath, and within each breath the four phases sample end-expiration, mid-inspiration,
end-inspiration and mid-expiration. breath(t) = (1 - cos(2 pi t / 4 s)) / 2 moves the
diaphragm domes, liver and spleen down by up to BREATH_AMPLITUDE_MM (12 mm), the kidneys
and heart part of that, and raises the sternum and the front of the ribs by up to
RIB_LIFT_MM (4 mm): the diaphragm and the rib cage, the two motions the seed simulators
drive. A real VCUG fills over minutes and voids in under a minute; the stages are
compressed so a trainee sees both processes in one loop, each at every breathing state.

Grid: 1.5 mm isotropic voxels, 161 x 113 x 267 (x, y, z; 241.5 x 169.5 x 400.5 mm), 9.7 MB
per phase as int16. Ribs (5-8 mm) and the distended urethra (5-8 mm) span several voxels,
while the 24 distinct volumes build in well under 30 s on two cores and fit in memory
together (233 MB); a 1 mm grid would cost 3.4 times both.

Contrast encoding, for the renderer: voxels at or above CONTRAST_BASE_HU (2500, the case's
`materials.contrast_min_hu`) are water-density tissue holding iodine at
    iodine_mg_per_ml = (HU - 2500) / 10            (see `iodine_mg_per_ml`),
so the instilled 150 mg/mL reads 4000 HU, and a voxel half filled at the bladder wall reads
2500 + 10 x 75 = 3250 HU (its iodine mass is kept; the rest of it counts as water).
Everything else stays below 2500 HU: cortical bone is 1500 HU, the catheter 600 HU.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np

from ..errors import FluorosimError
from . import anatomy, child_skeleton, shapes
from .anatomy import BREATH_AMPLITUDE_MM, RIB_LIFT_MM
from .volume import Volume

#: Bump when the drawing changes in a way the source digest would not catch.
GENERATOR_VERSION = 1

CONTRAST_BASE_HU = 2500.0
HU_PER_MG_PER_ML = 10.0
#: Iodine in the instilled contrast (mg/mL), as in configs/cases/child-torso-vcug.yaml.
CONTRAST_MG_PER_ML = 150.0
#: Less iodine than this in a voxel (mg/mL) is left as tissue, not marked as contrast.
MIN_MARKED_MG_PER_ML = 1.0

BREATH_PERIOD_S = 4.0
PHASE_STEP_S = 1.0
SPACING_MM = 1.5
#: Voxels along x, y, z: odd, so the midline and the centre of the volume are voxel centres.
GRID_SHAPE_XYZ = (161, 113, 267)


@dataclass(frozen=True)
class Stage:
    """One stage of the voiding cystourethrogram."""

    name: str
    bladder_ml: float
    contrast: bool
    voiding: bool
    catheter: bool


#: Catheter in and bladder drained; contrast instilled through it to the capacity of a 7
#: year old (about 250 mL); catheter out, voiding with the urethra distended; a small
#: post-void residual.
STAGES = (
    Stage("bladder drained", 10.0, False, False, True),
    Stage("filling", 80.0, True, False, True),
    Stage("filling", 160.0, True, False, True),
    Stage("full", 250.0, True, False, True),
    Stage("voiding begins", 235.0, True, True, False),
    Stage("voiding", 160.0, True, True, False),
    Stage("voiding", 80.0, True, True, False),
    Stage("post-void residual", 15.0, True, False, False),
)
PHASES_PER_STAGE = int(round(BREATH_PERIOD_S / PHASE_STEP_S))
#: The whole sequence (s): the last phase lasts PHASE_STEP_S like the others, so a case
#: that loops starts again at this time, not at the last time stamp.
SEQUENCE_S = len(STAGES) * PHASES_PER_STAGE * PHASE_STEP_S

NAMES = ("child-torso",)


def iodine_mg_per_ml(hu):
    """Iodine concentration (mg/mL) a voxel of the built-in patient holds; 0 below the contrast base."""
    return np.maximum((np.asarray(hu, np.float32) - CONTRAST_BASE_HU) / HU_PER_MG_PER_ML, 0.0)


def breath_at(t_s: float) -> float:
    """Breathing state at time t: 0 end-expiration, 1 end-inspiration."""
    return float((1.0 - np.cos(2.0 * np.pi * t_s / BREATH_PERIOD_S)) / 2.0)


@dataclass(frozen=True)
class PhaseSpec:
    time_s: float
    stage: int
    breath: float

    @property
    def file_name(self) -> str:
        # Mid-inspiration and mid-expiration are the same geometry: they share one file.
        return f"stage{self.stage}-breath{int(round(self.breath * 1000)):04d}.mha"


def timeline() -> list[PhaseSpec]:
    """The phases in time order: each VCUG stage held for one breath, sampled every PHASE_STEP_S."""
    out = []
    for k in range(len(STAGES) * PHASES_PER_STAGE):
        t = k * PHASE_STEP_S
        out.append(PhaseSpec(t, k // PHASES_PER_STAGE, round(breath_at(t), 6)))
    return out


def grid() -> shapes.Grid:
    return shapes.Grid.centred(GRID_SHAPE_XYZ, SPACING_MM)


def cache_key() -> str:
    """Generator version, parameters and a digest of the drawing code, hashed."""
    h = hashlib.sha256()
    params = dict(version=GENERATOR_VERSION, spacing=SPACING_MM, grid=GRID_SHAPE_XYZ, seed=anatomy.SEED,
                  stages=[s.__dict__ for s in STAGES], step=PHASE_STEP_S, period=BREATH_PERIOD_S,
                  amplitude=BREATH_AMPLITUDE_MM, rib_lift=RIB_LIFT_MM, contrast=[CONTRAST_BASE_HU, HU_PER_MG_PER_ML, CONTRAST_MG_PER_ML],
                  numpy=np.__version__.split(".")[0])
    h.update(json.dumps(params, sort_keys=True).encode())
    here = Path(__file__).parent
    for module in ("builtin.py", "anatomy.py", "child_skeleton.py", "shapes.py"):
        h.update((here / module).read_bytes())
    return h.hexdigest()[:16]


class Builder:
    """Draws the phases; the static parts once, each breathing state once, each phase cheaply."""

    def __init__(self, progress: Callable[[str], None] | None = None):
        self.progress = progress or (lambda message: None)
        self.grid = grid()
        self.progress("drawing the body and skeleton")
        self.static = anatomy.static_soft(self.grid, np.random.default_rng(anatomy.SEED))
        self.skeleton = child_skeleton.skeleton(self.grid)
        self._breaths: dict[float, tuple[shapes.Layer, shapes.Layer, np.ndarray]] = {}

    def breathing_state(self, breath: float) -> tuple[shapes.Layer, shapes.Layer, np.ndarray]:
        """Soft tissue, rib cage and the two composited (HU, float32) at one breathing state, drawn once and kept."""
        if breath not in self._breaths:
            self.progress(f"drawing the breathing organs and ribs at breath {breath:.2f}")
            soft = self.static.copy()
            anatomy.paint_breathing(soft, breath)
            ribs = child_skeleton.rib_cage(self.grid, breath)
            self._breaths[breath] = soft, ribs, ribs.over(self.skeleton.over(soft.value))
        return self._breaths[breath]

    def phase(self, spec: PhaseSpec) -> np.ndarray:
        """The int16 HU array (nz, ny, nx) of one phase."""
        stage = STAGES[spec.stage]
        soft, ribs, composited = self.breathing_state(spec.breath)
        soft = soft.copy()
        sl, fill = anatomy.paint_bladder(soft, stage.bladder_ml, stage.voiding, stage.catheter)
        # Only the bladder's box changed: lay the bones over it again there.
        hu = composited.copy()
        hu[sl] = ribs.over(self.skeleton.over(soft.value[sl], sl), sl)
        if stage.contrast:
            iodine = CONTRAST_MG_PER_ML * fill
            box = hu[sl]
            marked = iodine >= MIN_MARKED_MG_PER_ML
            box[marked] = CONTRAST_BASE_HU + HU_PER_MG_PER_ML * iodine[marked]
        return np.clip(np.rint(hu), -1024, 32767).astype(np.int16)


def _write_mha(path: Path, hu: np.ndarray, T: np.ndarray) -> None:
    import SimpleITK as sitk
    image = sitk.GetImageFromArray(hu)
    image.SetSpacing([float(s) for s in np.linalg.norm(T[:3, :3], axis=0)])
    image.SetOrigin([float(o) for o in T[:3, 3]])
    image.SetDirection([float(d) for d in (T[:3, :3] / np.linalg.norm(T[:3, :3], axis=0)).ravel()])
    sitk.WriteImage(image, str(path), True)


def load_mha(path: Path) -> Volume:
    """A phase file back as a Volume (int16 HU, T_ct_from_voxel from spacing, direction, origin)."""
    import SimpleITK as sitk
    try:
        image = sitk.ReadImage(str(path))
    except RuntimeError:
        raise FluorosimError(f"{path}: cannot read this cached phase; delete the folder {path.parent} "
                             "and the built-in patient is rebuilt on next use") from None
    hu = sitk.GetArrayFromImage(image)
    T = np.eye(4)
    direction = np.array(image.GetDirection()).reshape(3, 3)
    T[:3, :3] = direction * np.array(image.GetSpacing())
    T[:3, 3] = image.GetOrigin()
    return Volume(hu.astype(np.int16, copy=False), T, source=str(path))


def distinct_volumes() -> int:
    """How many different CT volumes the timeline's phases are drawn from (phases repeat some)."""
    return len({s.file_name for s in timeline()})


#: Free space the build needs (MB): its phases take about 35 MB compressed, and the work folder
#: holds them all before the rename.
BUILD_FREE_MB = 100


def build(target: Path, progress: Callable[[str], None] | None = None) -> None:
    """Build every phase into the folder `target` (created here, atomically: all or nothing)."""
    progress = progress or (lambda message: None)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        work = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=target.parent))
    except OSError as e:
        raise FluorosimError(f"{target.parent}: cannot create the cache folder of the built-in patient "
                             f"({e.strerror or e}); check the data folder in configs/appliance.yaml") from None
    try:
        # Refused before drawing, in our words: on a full disk SimpleITK's writer prints its own
        # lines to stderr before it raises, and a minute of drawing would be lost.
        if shutil.disk_usage(target.parent).free < BUILD_FREE_MB * 2**20:
            raise OSError(errno.ENOSPC, f"under {BUILD_FREE_MB} MB free")
        builder = Builder(progress)
        specs = timeline()
        written: set[str] = set()
        distinct = distinct_volumes()
        T = builder.grid.T_ct_from_voxel
        # Compressing and writing one phase overlaps drawing the next (the second core);
        # at most two phases wait, so memory stays bounded.
        with ThreadPoolExecutor(max_workers=1) as writer:
            pending = []
            for spec in specs:
                if spec.file_name in written:
                    continue
                # Counted in volumes, not phases: phases that share a stage and a breath share a volume.
                progress(f"volume {len(written) + 1}/{distinct} of {len(specs)} phases "
                         f"({spec.file_name[:-4]}): {STAGES[spec.stage].name}")
                pending.append(writer.submit(_write_mha, work / spec.file_name, builder.phase(spec), T))
                written.add(spec.file_name)
                if len(pending) >= 2:
                    pending.pop(0).result()
            for job in pending:
                job.result()
        manifest = {"name": target.name, "phases": [
            {"time_s": s.time_s, "file": s.file_name, "stage": STAGES[s.stage].name, "breath": s.breath}
            for s in specs]}
        (work / "manifest.json").write_text(json.dumps(manifest, indent=1))
        os.chmod(work, 0o755)      # mkdtemp makes it private; the renderer may run as another user
        try:
            os.rename(work, target)
        except OSError:
            if not (target / "manifest.json").is_file():
                raise
            # Another process finished the same build first; its result is identical.
            shutil.rmtree(work, ignore_errors=True)
    except (OSError, RuntimeError) as e:
        # RuntimeError: SimpleITK's writer reports a full disk or an I/O error this way.
        shutil.rmtree(work, ignore_errors=True)
        reason = getattr(e, "strerror", None) or str(e).strip().splitlines()[-1]
        raise FluorosimError(f"{target.parent}: cannot write the built-in patient ({reason}); "
                             f"check that the data folder is writable and has {BUILD_FREE_MB} MB free") from None
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise


def builtin_phases(name: str, cache_dir: Path,
                   progress: Callable[[str], None] | None = None) -> list[tuple[float, Callable[[], Volume]]]:
    """The phases of built-in patient `name` ("child-torso") as (time_s, loader) pairs; builds and caches on first use.

    Each loader reads its phase from the cache when called and returns a fresh Volume.
    """
    if name not in NAMES:
        raise FluorosimError(f"no built-in patient called {name!r}; the built-in patients are: {', '.join(NAMES)}")
    cache_dir = Path(cache_dir)
    target = cache_dir / f"{name}-{cache_key()}"
    manifest_path = target / "manifest.json"
    if not manifest_path.is_file():
        started = time.perf_counter()
        if progress:
            progress(f"building the built-in patient {name} (first use on this machine) in {target}")
        build(target, progress)
        if progress:
            progress(f"built {name} in {time.perf_counter() - started:.1f} s")
        for old in cache_dir.glob(f"{name}-*"):
            if old != target and old.is_dir() and (old / "manifest.json").is_file():
                shutil.rmtree(old, ignore_errors=True)
    try:
        manifest = json.loads(manifest_path.read_text())
        phases = [(float(p["time_s"]), target / p["file"]) for p in manifest["phases"]]
    except (OSError, ValueError, KeyError, TypeError):
        raise FluorosimError(f"{manifest_path}: damaged cache of the built-in patient; delete the folder {target} "
                             "and it is rebuilt on next use") from None
    for _, path in phases:
        if not path.is_file():
            raise FluorosimError(f"{path}: missing from the cache of the built-in patient; delete the folder "
                                 f"{target} and it is rebuilt on next use")
    return [(t, partial(load_mha, path)) for t, path in phases]
