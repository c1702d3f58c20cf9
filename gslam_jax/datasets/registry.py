"""The registry of frame sources: where a run's frames come from.

Every module of ``gslam_jax.datasets`` that provides a source declares it at module level as
``SOURCE = DataSource(...)``: its name (``--source NAME``), whether it is simulated, whether its
frames are stereo images (through the OpenCV front-end), which options it takes, and its
``load``. The registry finds the declarations by importing the package's modules, so adding a
source touches one file: a new module here with its ``SOURCE``. Dataset modules import no JAX,
so the command line can list the sources before JAX is loaded.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import pkgutil
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any, Callable, NamedTuple

from gslam_jax.config import Config, ConfigError

if TYPE_CHECKING:
    from gslam_jax.run import Run

__all__ = ["Source", "LoadedSource", "DataSource", "Progress", "sources", "source_names",
           "get_source", "discover", "check_source", "stereo_settings", "RUN_FILE"]

Progress = Callable[[int, int], None]

RUN_FILE = "run-file"  # the source of a native .npz Run file (the positional argument)


@dataclass(frozen=True)
class Source:
    """A request for frames: which source and its options (the command line's source arguments).

    ``seed`` is the simulation seed (None: 0); it only applies to simulated sources and to
    ``--gps sim``. ``noise_seed`` (sources that declare ``noise_seed``) draws the VO and sensor
    noise from another seed than the world and path: the same terrain driven again.
    ``max_frames`` cuts the sources that declare ``cuts_frames``. A Run file is
    ``Source(run_file=path)`` (its source is ``RUN_FILE``). ``topics``: (role, topic name)
    pairs for the sources that declare ``topics`` (``--topic ROLE=NAME``; name '' for none).
    """

    run_file: Path | None = None
    source: str = "sim"
    course: str = "mars-yard-a"
    path: Path | None = None
    sequence: str | None = None
    seed: int | None = None
    max_frames: int | None = None
    on_bad_frame: str = "error"
    noise_seed: int | None = None
    topics: tuple[tuple[str, str], ...] = ()

    @property
    def name(self) -> str:
        """The registered source this request reads."""
        return RUN_FILE if self.run_file is not None else self.source

    @property
    def spec(self) -> DataSource:
        return get_source(self.name)

    @property
    def simulated(self) -> bool:
        return self.spec.simulated

    @property
    def images(self) -> bool:
        """Frames come from stereo images through the OpenCV front-end."""
        return self.spec.images

    @property
    def sim_seed(self) -> int:
        return 0 if self.seed is None else self.seed

    @property
    def sim_noise_seed(self) -> int:
        """The seed of the VO and sensor noise: ``noise_seed``, else the simulation seed."""
        return self.sim_seed if self.noise_seed is None else self.noise_seed


class LoadedSource(NamedTuple):
    """What a source's ``load`` returns."""

    run: Run
    description: str          # e.g. "KITTI DIR sequence 00", printed and in summary.json
    sim_info: Any | None = None  # datasets.sim.SimInfo for the simulator (simulation.json)
    kitti_frame: Any | None = None  # datasets.kitti.KittiFrame, for trajectory_kitti.txt


@dataclass(frozen=True)
class DataSource:
    """One registered source of frames.

    ``path``: what ``--path`` names for this source (e.g. "KITTI odometry folder"), None when
    it takes no path; ``path_required``: it cannot load without one. ``sequence``: it takes
    ``--sequence``. ``cuts_frames``: ``--max-frames`` applies. ``noise_seed``: it takes
    ``--noise-seed``. ``topics``: it takes ``--topic ROLE=NAME``. ``load(request, config,
    progress)`` returns the Run (after the front-end for image sources).
    """

    name: str
    help: str
    load: Callable[[Source, Config, Progress | None], LoadedSource]
    simulated: bool = False
    images: bool = False
    path: str | None = None
    path_required: bool = True
    sequence: bool = False
    cuts_frames: bool = True
    noise_seed: bool = False
    topics: bool = False


def discover(package: ModuleType) -> dict[str, DataSource]:
    """The ``SOURCE`` of every module of ``package``, by name (modules without one are not
    sources); a name declared twice is an error."""
    found: dict[str, DataSource] = {}
    for info in sorted(pkgutil.iter_modules(package.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"{package.__name__}.{info.name}")
        spec = getattr(module, "SOURCE", None)
        if not isinstance(spec, DataSource):
            continue
        if spec.name in found:
            raise RuntimeError(f"source '{spec.name}' is declared twice ({module.__name__})")
        found[spec.name] = spec
    return found


@functools.cache
def sources() -> dict[str, DataSource]:
    """Every registered source by name: the sources of ``gslam_jax.datasets``."""
    import gslam_jax.datasets

    return discover(gslam_jax.datasets)


def source_names(command_line: bool = True) -> tuple[str, ...]:
    """The names ``--source`` accepts (``command_line``: without the Run file, which is the
    positional argument), simulated sources first."""
    specs = sources().values()
    return tuple(s.name for s in sorted(specs, key=lambda s: (not s.simulated, s.name))
                 if not (command_line and s.name == RUN_FILE))


def get_source(name: str) -> DataSource:
    try:
        return sources()[name]
    except KeyError:
        raise ConfigError(f"unknown source {name!r}; known sources: "
                          f"{', '.join(source_names())}") from None


def _names(predicate: Callable[[DataSource], bool]) -> str:
    return "/".join(s for s in source_names() if predicate(get_source(s)))


def check_source(src: Source, config: Config | None = None, gps: str | None = None) -> None:
    """ConfigError for options the source would silently ignore: source options beside a Run
    file, ``--path``/``--sequence``/``--max-frames`` for a source that takes none, ``--seed``
    where nothing is simulated, [stereo] or [rig] settings for a source without images; and for a
    missing ``--path``."""
    spec = src.spec
    if src.run_file is not None:
        extra = [opt for opt, given in (("--source", src.source != Source.source),
                                        ("--path", src.path is not None),
                                        ("--sequence", src.sequence is not None),
                                        ("--course", src.course != Source.course),
                                        ("--max-frames", src.max_frames is not None),
                                        ("--noise-seed", src.noise_seed is not None),
                                        ("--topic", bool(src.topics))) if given]
        if extra:
            raise ConfigError(f"{src.run_file}: a Run file is used as it is; {', '.join(extra)} "
                              "only apply without one (drop them, or re-create the Run with "
                              "--save-run)")
    else:
        if src.path is not None and spec.path is None:
            raise ConfigError(f"--path is for --source {_names(lambda s: s.path is not None)}, "
                              f"not --source {src.source}")
        if src.sequence is not None and not spec.sequence:
            raise ConfigError(f"--sequence is for --source {_names(lambda s: s.sequence)}, not "
                              f"--source {src.source}")
        if src.noise_seed is not None and not spec.noise_seed:
            raise ConfigError(f"--noise-seed is for --source {_names(lambda s: s.noise_seed)}, "
                              f"not --source {src.source}")
        if src.topics and not spec.topics:
            raise ConfigError(f"--topic is for --source {_names(lambda s: s.topics)}, not "
                              f"--source {src.source}")
        if src.max_frames is not None and not spec.cuts_frames:
            raise ConfigError(f"--max-frames does not apply to --source {src.source}")
        if src.path is None and spec.path is not None and spec.path_required:
            raise ConfigError(f"--source {src.source} needs --path ({spec.path})")
    what = str(src.run_file) if src.run_file is not None else f"--source {src.source}"
    if src.seed is not None and not spec.simulated and str(gps) != "sim":
        raise ConfigError(f"--seed {src.seed}: {what} is not simulated, so the simulation seed "
                          "would be ignored; the filter's seed is filter.seed (--set "
                          "filter.seed=N)")
    images = ', '.join(s for s in source_names() if get_source(s).images)
    if config is not None and not config.stereo.is_default() and not spec.images:
        raise ConfigError(f"[stereo] {', '.join(config.stereo.given())}: settings apply to "
                          f"stereo images (--source {images}); {what} has none")
    if config is not None and not config.rig.is_default() and not spec.images:
        raise ConfigError(f"[rig] {', '.join(config.rig.given())}: the camera mount applies to "
                          f"stereo images (--source {images}); {what} has none")


def stereo_settings(config: Config, default: Any) -> Any:
    """The source's ``vo.stereo.DenseStereoParams`` ``default`` with the config's [stereo]
    settings (0 or "": the source's own); each [stereo] key is the field of that name."""
    st = config.stereo
    return dataclasses.replace(default, **{k: getattr(st, k) for k in st.given()})
