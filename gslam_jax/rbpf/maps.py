"""The map-store seam: the only code that knows which store holds the particles' maps.

Three stores sit behind it (``FilterConfig.store``): "dense" (``densestore``: a whole
[H, W] map of k and S per particle), "shared" (``tilestore``: copy-on-write tiles in one pool
behind per-particle page tables) and "window" (``windowstore``: each particle's map as its
path over the shared local maps, with a window of cells around it materialised). ``FilterState.maps`` holds either (``Maps``); the kernel and
the host driver reach it only through the functions here, which dispatch to the store:

* in the filter: ``init`` (empty maps, or a prior map in every particle), ``read`` (the map
  cells under a footprint: eq. 26's priors, eq. 31's borrowed known cells), ``write``
  (eq. 14), ``sample_known`` (eq. 31's uniform known cells), ``finish_update`` (after an update's
  writes), ``resample`` (each particle takes its ancestor's maps), ``particle_map``,
  ``to_dense``, ``known_bits``, ``status``;
* on the host: ``choose_store`` (``store = "auto"``), ``pool_tiles``, ``whole_maps_tiles``,
  ``prior_tiles``, ``map_bytes`` (what a store allocates), ``peak_bytes``, ``check_memory``
  (before allocating), ``check_status`` and ``pool_ran_out`` (the shared store's error bits,
  after a run or a chunk), ``grow_pool`` and ``PoolGrowth`` (an automatic pool that is running
  low, grown between chunks of frames).
"""

from __future__ import annotations

import warnings
from typing import Union

import jax.numpy as jnp
import numpy as np
from jax import Array

from gslam_jax.config import ConfigError
from gslam_jax.errors import InputError
from gslam_jax.rbpf import densestore, tilebytes, tilesample, tilestore, windowstore
from gslam_jax.rbpf.densestore import DenseMaps
from gslam_jax.rbpf.tilestore import TileStore
from gslam_jax.rbpf.types import FilterConfig, FilterState, Observation
from gslam_jax.rbpf.windowstore import WindowMaps

__all__ = ["Maps", "DenseMaps", "TileStore", "MapStoreNotice", "init", "read", "write",
           "sample_known", "finish_update", "resample", "particle_map", "to_dense", "known_bits",
           "status", "free_tiles", "page_window", "pool_tiles", "whole_maps_tiles", "prior_tiles",
           "map_bytes", "peak_bytes", "choose_store", "check_memory", "check_status",
           "pool_ran_out", "grow_pool", "PoolGrowth", "HistoryGrowth", "LIVE_HISTORY",
           "live_growth",
           "WindowMaps", "resolve_history",
           "WindowStoreError"]

Maps = Union[DenseMaps, TileStore, WindowMaps]
"""The particles' maps (``FilterState.maps``): the dense, shared tile or window store."""

AUTO_POOL_MAPS = 4  # ``pool_tiles``: whole maps of shared history an automatic pool holds
LIVE_HISTORY = 64   # local maps a live run's window-store history holds before it first grows


class MapStoreNotice(UserWarning):
    """A note on the map store: ``[map] store = "auto"`` chose the shared tile store (the dense
    maps would not fit), or an automatic pool grew (``grow_pool``)."""


def _shared(maps: Maps) -> bool:
    return isinstance(maps, TileStore)


def _window(maps: Maps) -> bool:
    return isinstance(maps, WindowMaps)


class WindowStoreError(InputError):
    """The window store could not hold a run's maps (its window or its history)."""


def _check_window(cfg: FilterConfig, prior) -> None:
    """ConfigError for what the window store does not do: eq. 31 (it draws known cells from
    the whole map, which the store does not hold), a prior map, an unsized history."""
    if cfg.unknown_cells == "sample":
        raise ConfigError('[map] store = "window" supports [filter] unknown_cells = "ignore" '
                          '(eq. 30) only: eq. 31 draws known cells from the whole map, which '
                          'this store does not hold; use store "dense" or "shared"')
    if prior is not None:
        raise ConfigError('[map] store = "window" cannot start from a prior map; use store '
                          '"dense" or "shared"')
    if cfg.pool_tiles < 1:
        raise ConfigError('[map] store = "window" needs its history sized: [map] pool_tiles = '
                          'the local maps the run has (a run sizes it itself and a live run '
                          'grows it, ``maps.resolve_history``, ``maps.HistoryGrowth``)')


def resolve_history(cfg: FilterConfig, num_updates: int, local_maps=None) -> FilterConfig:
    """The window store's history (``[map] pool_tiles``, 0: automatic) sized to the run's
    ``num_updates`` local maps, so that ``map_bytes`` is the whole run's need before it
    starts, and its window to the reach of the observed cells of the run's ``local_maps``
    [n, L, L, 2] (``windowstore.observed_reach``; None: the local map's diagonal); other
    stores unchanged."""
    if cfg.store != "window":
        return cfg
    if local_maps is not None:
        cfg = cfg._replace(observed_reach=min(windowstore.observed_reach(local_maps),
                                              cfg.reach))
    if cfg.pool_tiles:
        return cfg
    return cfg._replace(pool_tiles=max(int(num_updates), 1))


def init(cfg: FilterConfig, prior: tuple[Array, Array] | None = None) -> Maps:
    """The store ``cfg.store`` with J empty maps, or with J times the map ``prior`` = (k, S)
    [H, W] (map reuse: the dense store copies it into every particle's map, the shared store
    holds its known tiles once for all, ``tilestore.with_prior``)."""
    bits = cfg.unknown_cells == "sample"
    if prior is not None and tuple(prior[0].shape) != tuple(cfg.map_shape):
        raise ValueError(f"prior map of shape {tuple(prior[0].shape)} does not match the "
                         f"filter's map shape {cfg.map_shape}")
    if cfg.store == "window":
        _check_window(cfg, prior)
        return windowstore.init(cfg)
    if cfg.store == "shared":
        store = tilestore.init(cfg.num_particles, cfg.map_shape, cfg.tile, pool_tiles(cfg),
                               bits)
        return store if prior is None else tilestore.with_prior(store, *prior)
    return densestore.init(cfg.num_particles, cfg.map_shape, bits, prior)


def read(maps: Maps, particles: Array, cells_: Array, on_map: Array, cfg: FilterConfig
         ) -> tuple[Array, Array]:
    """(k, S) [n, M] at flat map cells cells_ [n, M] of particles [n]; 0 where not on_map."""
    if _shared(maps):
        return tilestore.read(maps, particles, cells_, on_map, cfg.map_shape[1])
    if _window(maps):
        return windowstore.read(maps, particles, cells_, on_map, cfg.map_shape[1])
    return densestore.read(maps, particles, cells_, on_map)


def write(maps: Maps, particles: Array, cells_: Array, k: Array, S: Array,
          cfg: FilterConfig) -> Maps:
    """Eq. 14: add (k, S) [M] at cells_ [n, M] (H*W: off the map) of particles [n]. The
    shared store first gives each written page a tile of its own (copy-on-write) and
    refreshes the written tiles' known-cell bits."""
    if _shared(maps):
        HW = cfg.map_shape[0] * cfg.map_shape[1]
        return tilestore.write(maps, particles, jnp.minimum(cells_, HW - 1), cells_ < HW, k, S,
                               cfg.map_shape[1], page_window(cfg))
    if _window(maps):
        return windowstore.write(maps, particles, cells_, k, S, cfg.map_shape)
    return densestore.add(maps, particles, cells_, k, S)


def sample_known(maps: Maps, rows: Array, u: Array, cfg: FilterConfig) -> tuple[Array, Array]:
    """Uniform known cells of the maps of particles ``rows`` [n], one per uniform of ``u``
    [n, S] ("sample" mode, eq. 31): (flat map cells [n, S], known cells [n]). Both stores draw
    the same cells (``unknown.sample_known_cells``; the shared store without scanning whole
    maps, ``tilesample``); where a map has none the cells are meaningless."""
    if _shared(maps):
        return tilesample.sample_known(maps, rows, u, cfg.map_shape)
    if _window(maps):
        _check_window(cfg, None)
    return densestore.sample_known(maps, rows, u, cfg.map_shape[1])


def finish_update(maps: Maps, pose: Array, cfg: FilterConfig,
                  obs: Observation | None = None) -> Maps:
    """After an update from ``pose`` [J, 3] with the local map ``obs`` wrote the maps: the
    dense store refreshes its known-cell bits around each footprint and widens its written
    rows; the shared store has nothing left to do (its writes refreshed the bits of the tiles
    they wrote); the window store records the update and moves each window, refilling the
    cells it takes in (``windowstore.finish_update``; it needs ``obs``)."""
    if _shared(maps):
        return maps
    if _window(maps):
        if obs is None:
            raise ValueError("maps.finish_update: the window store needs the update's "
                             "observation (obs)")
        return windowstore.finish_update(maps, pose, obs, cfg)
    return densestore.finish_update(maps, pose, cfg)


def resample(maps: Maps, ancestors: Array) -> Maps:
    """Particle i takes the maps of particle ancestors[i] (``ancestors`` keeps survivors in
    place, ``resampling.keep_in_place``): dense maps copied over the written rows, or the
    shared store's page tables gathered."""
    if _shared(maps):
        return tilestore.resample(maps, ancestors)
    if _window(maps):
        return windowstore.resample(maps, ancestors)
    return densestore.resample(maps, ancestors)


def particle_map(state: FilterState, j: Array | int, cfg: FilterConfig) -> tuple[Array, Array]:
    """(k, S) [H, W] of particle ``j``, from either store."""
    maps = state.maps
    if _window(maps):
        return windowstore.particle_map(maps, j, cfg)
    if not _shared(maps):
        return maps.k[j], maps.S[j]
    one = maps._replace(page=maps.page[jnp.asarray(j)][None])
    k, S, _ = tilestore.to_dense(one, cfg.map_shape)
    return k[0], S[0]


def to_dense(maps: Maps, cfg: FilterConfig) -> tuple[Array, Array, Array]:
    """Every particle's maps: k, S [J, H, W] and known-cell bits [J, H/8, W/8, 2] ([J, 0, 0, 2]
    unless "sample" mode)."""
    if _shared(maps):
        return tilestore.to_dense(maps, cfg.map_shape)
    if _window(maps):
        return windowstore.to_dense(maps, cfg)
    return maps.k, maps.S, maps.known_bits


def known_bits(maps: Maps, particles: Array, cfg: FilterConfig) -> Array:
    """Known-cell bits [n, H/8, W/8, 2] of the whole maps of ``particles`` [n] (eq. 31's
    bitmasks, ``unknown.pack_known``'s layout), whichever store holds them."""
    if _shared(maps):
        return tilestore.known_bits(maps, particles, cfg.map_shape)
    return densestore.known_bits(maps, particles)


def status(maps: Maps) -> Array:
    """The shared or window store's sticky error bits (``check_status``); 0 for the dense
    store."""
    return maps.status if _shared(maps) or _window(maps) else jnp.int32(0)


def free_tiles(maps: Maps) -> Array:
    """[] int32 free tiles in the shared store's pool; 0 for the dense store."""
    return maps.n_free if _shared(maps) else jnp.int32(0)


def page_window(cfg: FilterConfig) -> int:
    """Pages per side one particle's update can write in the shared store (its reach)."""
    return tilestore.window_tiles(cfg.reach, cfg.tile)


def pool_tiles(cfg: FilterConfig) -> int:
    """Tiles in the shared store's pool (``cfg.pool_tiles``; 0: automatic). Automatic: four
    whole maps of shared history plus, for every particle, the most tiles one update can give
    it (``page_window`` squared: after a resampling each particle copies the tiles under its
    footprint); never more than every particle's whole map (which cannot run out)."""
    if cfg.pool_tiles:
        return cfg.pool_tiles
    ty, tx = tilestore.pages_per_side(cfg.map_shape, cfg.tile)
    auto = AUTO_POOL_MAPS * ty * tx + cfg.num_particles * page_window(cfg) ** 2
    return min(auto, whole_maps_tiles(cfg))


def whole_maps_tiles(cfg: FilterConfig, particles: int | None = None) -> int:
    """Tiles of ``particles`` (default: every particle's) whole maps in the shared store: a
    pool that size cannot run out."""
    ty, tx = tilestore.pages_per_side(cfg.map_shape, cfg.tile)
    return (cfg.num_particles if particles is None else particles) * ty * tx


def prior_tiles(k, cfg: FilterConfig) -> int:
    """Pool tiles of the shared store that a prior map k [H, W] (on the filter's lattice)
    takes: its tiles with a known cell (host side)."""
    return tilestore.prior_tiles(k, cfg.tile)


def map_bytes(cfg: FilterConfig) -> int:
    """Bytes the store ``cfg.store`` allocates for the particles' maps (``init``): the dense
    maps, or the shared store's pool (allocated up front), page tables and bookkeeping."""
    bits = cfg.unknown_cells == "sample"
    if cfg.store == "window":
        return windowstore.nbytes(cfg)
    if cfg.store == "shared":
        return tilebytes.nbytes(cfg.num_particles, cfg.map_shape, cfg.tile, pool_tiles(cfg),
                                bits)
    return densestore.nbytes(cfg.num_particles, cfg.map_shape, bits)


def peak_bytes(maps: Maps, cfg: FilterConfig) -> int:
    """Most bytes the maps held at once (host side): the dense maps (fixed), or the shared
    store's peak of live tiles plus its page tables and bookkeeping."""
    return tilebytes.peak_bytes(maps) if _shared(maps) else map_bytes(cfg)


def _gib(n: int) -> str:
    """``n`` bytes in GiB, readable however large (Python ints beyond float range too)."""
    return f"{n / 2**30:.1f}" if n < 2**50 else _large(n // 2**30)


def _large(n: int) -> str:
    """A whole number, as 1.23e45 beyond a billion (Python ints beyond float range too)."""
    if n < 10**9:
        return str(n)
    digits = str(n)
    return f"{digits[0]}.{digits[1:3]}e{len(digits) - 1}"


def choose_store(cfg: FilterConfig, available: int, what: str = "memory") -> FilterConfig:
    """Resolve ``store = "auto"``: dense when the dense maps fit in ``available`` bytes (of
    ``what``), else shared, saying so (``MapStoreNotice``). Other stores are kept."""
    if cfg.store != "auto":
        return cfg
    dense = cfg._replace(store="dense")
    need = map_bytes(dense)
    if need <= available:
        return dense
    shared = cfg._replace(store="shared")
    warnings.warn(f"[map] store = \"auto\": dense maps would need {need / 2**30:.1f} GiB, more "
                  f"than the {available / 2**30:.1f} GiB of {what}; using the shared tile store "
                  f"({pool_tiles(shared)} tiles, {map_bytes(shared) / 2**30:.2f} GiB)",
                  MapStoreNotice, stacklevel=2)
    return shared


def check_memory(cfg: FilterConfig, available: int, what: str = "memory",
                 extent: str = "") -> None:
    """ConfigError, before anything is allocated, when the particle maps alone (``map_bytes``)
    would exceed ``available`` bytes of ``what``; ``extent`` says what sized the map."""
    need = map_bytes(cfg)
    if need <= available:
        return
    if cfg.store == "window":
        C = windowstore.side(cfg)
        raise ConfigError(
            f"the window map store needs {need / 2**30:.2f} GiB ({cfg.num_particles} "
            f"particles x ({C} x {C} cells x 2 float32 + a path of {cfg.pool_tiles} poses) + "
            f"{cfg.pool_tiles} local maps of {cfg.max_observed} cells), more than this "
            f"machine's {available / 2**30:.1f} GiB of {what}; use fewer [filter] particles")
    if cfg.store == "shared":
        raise ConfigError(
            f"the shared map store's pool needs {need / 2**30:.1f} GiB ([map] pool_tiles = "
            f"{pool_tiles(cfg)} tiles of {cfg.tile} x {cfg.tile} cells), more than this "
            f"machine's {available / 2**30:.1f} GiB of {what}; lower [map] pool_tiles")
    H, W = cfg.map_shape
    raise ConfigError(
        f"the particle maps need {_gib(need)} GiB ({cfg.num_particles} particles x "
        f"{_large(H)} x {_large(W)} cells of {cfg.resolution:g} m x 2 float32), more than "
        f"this machine's {available / 2**30:.1f} GiB of {what}{extent}; use fewer [filter] "
        f"particles, a coarser [map] resolution, a smaller [map] margin or [map] store = "
        f"\"shared\"")


def check_status(status_bits: int | Array, cfg: FilterConfig, where: str = "",
                 automatic: bool = False) -> None:
    """Raise the host-side error for a store's ``status`` bits (0: fine); ``where`` prefixes
    the message (the frame, the tuning step); ``automatic``: the pool is a ``PoolGrowth``'s."""
    if cfg.store == "window":
        _window_status(int(status_bits), cfg, where)
        return
    tilebytes.check_status(status_bits, pool_tiles(cfg), where, automatic)


def pool_ran_out(status_bits) -> int:
    """1 + the index of the first of a chunk's per-frame ``status`` bits [n] that says the
    shared pool ran out of tiles; 0 if none does."""
    hit = (np.asarray(status_bits) & tilestore.POOL_EXHAUSTED) != 0
    return int(np.argmax(hit)) + 1 if hit.any() else 0


def _window_status(bits: int, cfg: FilterConfig, where: str) -> None:
    """WindowStoreError for the window store's status bits (0: fine)."""
    if bits & windowstore.MISSED:
        raise WindowStoreError(
            where + f"the window map store's window ({windowstore.side(cfg)} cells) missed "
            f"cells an update wrote: a particle moved more than [map] tile = {cfg.tile} cells "
            f"between local maps (or a local map reached past the {windowstore.reach(cfg)} "
            f"cells the window was sized for); raise [map] tile")
    if bits & windowstore.HISTORY_FULL:
        raise WindowStoreError(
            where + f"the window map store's history of [map] pool_tiles = {cfg.pool_tiles} "
            f"local maps is full; raise it to the run's local maps")
    if bits & windowstore.REFILL_OVERFLOW:
        raise WindowStoreError(
            where + "the window map store met more past local maps than one refill replays")


def grow_pool(maps_: Maps, cfg: FilterConfig, need_free: int, available: int
              ) -> tuple[Maps, FilterConfig] | None:
    """The shared store with at least ``need_free`` free tiles (host side, between chunks of
    frames): its pool doubled, or more where that is not enough, but never past every
    particle's whole map (a pool that size cannot run out). Returns the grown maps and the
    config with the new ``pool_tiles`` (a new static shape: the filter step recompiles), or
    None when nothing is to be done: the dense store, enough free tiles already, a pool at
    that cap, or no room in ``available`` bytes for the grown pool beside the old one."""
    if not _shared(maps_):
        return None
    have, free = pool_tiles(cfg), int(maps_.n_free)
    cap = whole_maps_tiles(cfg)
    if free >= need_free or have >= cap:
        return None
    new = min(max(2 * have, have - free + need_free), cap)
    grown = cfg._replace(pool_tiles=new)
    if map_bytes(cfg) + map_bytes(grown) > available:  # both live while the pool is copied
        return None
    return tilestore.grow(maps_, new), grown


class PoolGrowth:
    """An automatic (``[map] pool_tiles = 0``) shared pool grown between chunks of frames
    (``grow_pool``; ``slam.run_slam``, and ``online.Online`` with one-frame chunks), so that a
    long run does not run out of tiles. After each chunk the pool keeps at least twice the most
    tiles any chunk has taken so far (its free count at the start less the lowest at a frame's
    end, ``StepInfo.map_free``), plus one update's worth for every particle (taken and given
    back within a frame). A chunk that runs out all the same (its first, or a sudden spread of
    the particles) is run again from its start with the pool doubled (``regrow``; the caller
    keeps a copy of the chunk's starting state). Growing changes no value; the filter step
    recompiles for the new pool, and ``MapStoreNotice`` says so."""

    def __init__(self, available: int, what: str):
        self.available, self.what = available, what
        self.most_taken = 0
        self.free_before = 0

    @classmethod
    def automatic(cls, cfg: FilterConfig, pool_tiles_setting: int, available: int, what: str
                  ) -> "PoolGrowth | None":
        """A PoolGrowth for the shared store when ``[map] pool_tiles`` (``pool_tiles_setting``)
        is 0, the memory being ``available`` bytes of ``what``; None otherwise."""
        if cfg.store != "shared" or pool_tiles_setting:
            return None
        return cls(available, what)

    def before(self, maps_: Maps) -> None:
        """Note the pool's free tiles as a chunk starts."""
        self.free_before = int(free_tiles(maps_))

    def after(self, maps_: Maps, cfg: FilterConfig, map_free: Array | np.ndarray, frame: int
              ) -> tuple[Maps, FilterConfig]:
        """The maps and filter config for the next chunk, after the chunk whose per-frame
        free counts were ``map_free`` and which ended at ``frame``: grown when running low."""
        self.most_taken = max(self.most_taken, self.free_before - int(np.min(map_free)))
        need = 2 * self.most_taken + cfg.num_particles * page_window(cfg) ** 2
        grown = grow_pool(maps_, cfg, need, self.available)
        if grown is None:
            return maps_, cfg
        self._notice(f"frame {frame}: the shared map store's automatic pool grew", cfg, grown[1])
        return grown

    def regrow(self, start_maps: Maps, cfg: FilterConfig, start: int, frame: int
               ) -> tuple[Maps, FilterConfig] | None:
        """``start_maps`` (a copy of the maps as the chunk from frame ``start`` began) in a pool
        at least twice as large, for running the chunk again after it ran out of tiles at
        ``frame``; None when the memory given has no room for it beside the old pool."""
        grown = grow_pool(start_maps, cfg, 2 * pool_tiles(cfg), self.available)
        if grown is not None:
            self._notice(f"frame {frame}: the shared map store's automatic pool ran out; frames "
                         f"from {start} run again after it grew", cfg, grown[1])
        return grown

    def _notice(self, what: str, cfg: FilterConfig, grown: FilterConfig) -> None:
        warnings.warn(f"{what} from {pool_tiles(cfg)} to {pool_tiles(grown)} tiles "
                      f"({map_bytes(grown) / 2**20:.1f} MiB of {self.what}); the filter step "
                      f"compiles again for it. [map] pool_tiles = N fixes the pool's size",
                      MapStoreNotice, stacklevel=4)


class HistoryGrowth:
    """The window store's history grown between frames of a live run (``online.Online`` with
    ``[map] pool_tiles = 0``), whose local maps are not known before it starts: it starts at
    ``LIVE_HISTORY`` (``resolve_history``) and doubles whenever it is full, before the next
    update would overflow it. Growing changes no value; the filter step recompiles for the new
    history, and ``MapStoreNotice`` says so. Where the memory has no room for the doubled
    history, it is left full and the next update stops the run naming the setting."""

    def __init__(self, available: int, what: str):
        self.available, self.what = available, what

    @classmethod
    def automatic(cls, cfg: FilterConfig, pool_tiles_setting: int, available: int, what: str
                  ) -> "HistoryGrowth | None":
        """A HistoryGrowth for the window store when ``[map] pool_tiles``
        (``pool_tiles_setting``) is 0, the memory being ``available`` bytes of ``what``; None
        otherwise."""
        if cfg.store != "window" or pool_tiles_setting:
            return None
        return cls(available, what)

    def before(self, maps_: Maps) -> None:
        """Nothing to note as a chunk starts (``PoolGrowth``'s interface)."""

    def after(self, maps_: Maps, cfg: FilterConfig, map_free: Array | np.ndarray, frame: int
              ) -> tuple[Maps, FilterConfig]:
        """The maps and filter config for the next chunk, after the chunk that ended at
        ``frame``: the history doubled where it is full."""
        held = windowstore.history(cfg)
        if int(maps_.count) < held:
            return maps_, cfg
        grown = cfg._replace(pool_tiles=2 * held)
        if map_bytes(grown) > self.available:
            return maps_, cfg
        warnings.warn(f"frame {frame}: the window map store's history grew from {held} to "
                      f"{2 * held} local maps ({map_bytes(grown) / 2**20:.1f} MiB of "
                      f"{self.what}); the filter step compiles again for it. [map] pool_tiles "
                      f"= N fixes the history's size", MapStoreNotice, stacklevel=3)
        return windowstore.grow_history(maps_, 2 * held), grown


def live_growth(cfg: FilterConfig, pool_tiles_setting: int, available: int, what: str
                ) -> PoolGrowth | HistoryGrowth | None:
    """What a live run (``online.Online``) grows between frames for the store ``cfg.store``:
    the shared store's automatic pool (``PoolGrowth``), the window store's automatic history
    (``HistoryGrowth``), or nothing."""
    return (PoolGrowth.automatic(cfg, pool_tiles_setting, available, what)
            or HistoryGrowth.automatic(cfg, pool_tiles_setting, available, what))
