"""Volume geometry: the sample (reconstruction) frame."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import GeometryError

__all__ = ["VolumeGeometry"]


def _triple(value, name: str, *, positive: bool) -> tuple[float, float, float]:
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0:
        arr = np.repeat(arr, 3)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise GeometryError(f"{name} must be one finite number or three, got {value!r}")
    if positive and np.any(arr <= 0):
        raise GeometryError(f"{name} must be positive, got {value!r}")
    return tuple(float(a) for a in arr)


@dataclass(frozen=True)
class VolumeGeometry:
    """A regular voxel grid in the volume (sample) frame.

    Parameters
    ----------
    shape : (nz, ny, nx) ints
        Array shape of the volume ``f[z, y, x]``; each at least 2.
    voxel_size : float or (sz, sy, sx) floats
        Voxel pitch, **in array order** like ``shape``, in length units.
    offset : (x, y, z) floats
        World position of the volume centre, **in xyz order** (it is a point
        of the volume frame, like the geometry vectors).

    Notes
    -----
    Voxel ``(iz, iy, ix)`` has its centre at
    ``((ix - (nx-1)/2) sx, (iy - (ny-1)/2) sy, (iz - (nz-1)/2) sz) + offset``
    (``DESIGN.md`` §1).

    Examples
    --------
    >>> vg = VolumeGeometry((64, 64, 64), voxel_size=0.5)
    >>> vg.voxel_center(0, 0, 0)
    array([-15.75, -15.75, -15.75])
    """

    shape: tuple[int, int, int]
    voxel_size: tuple[float, float, float] = 1.0  # type: ignore[assignment]
    offset: tuple[float, float, float] = field(default=(0.0, 0.0, 0.0))

    def __post_init__(self) -> None:
        shape = tuple(self.shape) if np.ndim(self.shape) == 1 else None
        if (
            shape is None
            or len(shape) != 3
            or not all(isinstance(n, (int, np.integer)) and not isinstance(n, bool) for n in shape)
            or any(n < 2 for n in shape)
        ):
            raise GeometryError(
                f"shape must be three ints (nz, ny, nx), each >= 2, got {self.shape!r}"
            )
        object.__setattr__(self, "shape", tuple(int(n) for n in shape))
        object.__setattr__(self, "voxel_size", _triple(self.voxel_size, "voxel_size", positive=True))
        object.__setattr__(self, "offset", _triple(self.offset, "offset", positive=False))

    # -- derived quantities -------------------------------------------------
    @property
    def spacing_xyz(self) -> np.ndarray:
        """Voxel pitch as an (x, y, z) vector."""
        return np.array(self.voxel_size[::-1], dtype=np.float64)

    @property
    def extent_xyz(self) -> np.ndarray:
        """Full size of the grid (voxel edges to voxel edges), (x, y, z)."""
        return np.array(self.shape[::-1], dtype=np.float64) * self.spacing_xyz

    @property
    def n_voxels(self) -> int:
        return int(np.prod(self.shape))

    def voxel_center(self, iz, iy, ix) -> np.ndarray:
        """World (x, y, z) centre of voxel(s) ``(iz, iy, ix)``; broadcasts."""
        nz, ny, nx = self.shape
        sz, sy, sx = self.voxel_size
        ox, oy, oz = self.offset
        iz, iy, ix = np.broadcast_arrays(
            np.asarray(iz, np.float64), np.asarray(iy, np.float64), np.asarray(ix, np.float64)
        )
        return np.stack(
            [
                (ix - (nx - 1) / 2) * sx + ox,
                (iy - (ny - 1) / 2) * sy + oy,
                (iz - (nz - 1) / 2) * sz + oz,
            ],
            axis=-1,
        )

    def world_to_index(self, points) -> np.ndarray:
        """Continuous array indices ``(iz, iy, ix)`` of world points ``(..., 3)`` in xyz."""
        p = np.asarray(points, dtype=np.float64)
        if p.shape[-1] != 3:
            raise GeometryError(f"points must have a last axis of 3 (x, y, z), got shape {p.shape}")
        n_xyz = np.array(self.shape[::-1], np.float64)
        idx_xyz = (p - np.asarray(self.offset)) / self.spacing_xyz + (n_xyz - 1) / 2
        return idx_xyz[..., ::-1].copy()

    def coordinates(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """1D world coordinates of voxel centres along z, y, x (array order)."""
        nz, ny, nx = self.shape
        sz, sy, sx = self.voxel_size
        ox, oy, oz = self.offset
        return (
            (np.arange(nz) - (nz - 1) / 2) * sz + oz,
            (np.arange(ny) - (ny - 1) / 2) * sy + oy,
            (np.arange(nx) - (nx - 1) / 2) * sx + ox,
        )

    def binned(self, factor: int) -> "VolumeGeometry":
        """The grid with ``factor`` x coarser voxels covering the same box.

        The shape is divided by ``factor`` (rounded down, at least 2) and the
        voxel size multiplied by it; the centre does not move.
        """
        if not isinstance(factor, (int, np.integer)) or factor < 1:
            raise GeometryError(f"factor must be a positive int, got {factor!r}")
        shape = tuple(max(2, n // int(factor)) for n in self.shape)
        size = tuple(s * int(factor) for s in self.voxel_size)
        return VolumeGeometry(shape, size, self.offset)

    def check_volume(self, volume: np.ndarray, name: str = "volume") -> None:
        """Raise a clear error if ``volume`` does not match this grid."""
        from ..errors import ShapeError

        if not isinstance(volume, np.ndarray):
            raise ShapeError(f"{name} must be a numpy array of shape {self.shape}, got {type(volume).__name__}")
        if volume.shape != self.shape:
            raise ShapeError(f"{name} must have shape {self.shape} (nz, ny, nx), got {volume.shape}")
