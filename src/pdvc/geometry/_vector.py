"""Per-view vector geometry (ASTRA ``cone_vec`` / ``parallel3d_vec`` layout)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import GeometryError
from ._poses import rotvec_to_matrix

__all__ = ["VectorGeometry"]

_KINDS = ("cone", "parallel")
_ASTRA_TYPES = {"cone": "cone_vec", "parallel": "parallel3d_vec"}


def check_det_shape(det_shape) -> tuple[int, int]:
    try:
        shape = tuple(det_shape)
    except TypeError:
        shape = None
    if (
        shape is None
        or len(shape) != 2
        or not all(isinstance(n, (int, np.integer)) and not isinstance(n, bool) for n in shape)
        or any(n < 1 for n in shape)
    ):
        raise GeometryError(f"det_shape must be two positive ints (n_rows, n_cols), got {det_shape!r}")
    return int(shape[0]), int(shape[1])


@dataclass(frozen=True, eq=False)
class VectorGeometry:
    """Per-view geometry as rows of 12 numbers, immutable.

    Each row is ``(src, d, u, v)`` for cone beam (ASTRA ``cone_vec``) or
    ``(ray, d, u, v)`` for parallel beam (ASTRA ``parallel3d_vec``), every
    part a 3-vector ``(x, y, z)`` in the volume frame:

    * ``src`` the source position (cone) / ``ray`` the ray direction (parallel);
    * ``d`` the detector centre;
    * ``u`` the step from pixel ``(0, 0)`` to pixel ``(0, 1)`` (next column);
    * ``v`` the step from pixel ``(0, 0)`` to pixel ``(1, 0)`` (next row).

    Pixel ``(i, j)`` has its centre at
    ``d + (j - (n_cols-1)/2) u + (i - (n_rows-1)/2) v``.

    Parameters
    ----------
    vectors : (n_views, 12) array
        Stored as a read-only float64 copy.
    det_shape : (n_rows, n_cols)
    kind : {"cone", "parallel"}

    Every transformation (view selection, binning, poses) returns a new
    object; the vectors array is never written.
    """

    vectors: np.ndarray
    det_shape: tuple[int, int]
    kind: str = "cone"

    def __post_init__(self) -> None:
        if self.kind not in _KINDS:
            raise GeometryError(f"kind must be one of {_KINDS}, got {self.kind!r}")
        object.__setattr__(self, "det_shape", check_det_shape(self.det_shape))
        vec = np.array(self.vectors, dtype=np.float64, copy=True)
        if vec.ndim == 1 and vec.shape[0] == 12:
            vec = vec[None, :]
        if vec.ndim != 2 or vec.shape[1] != 12 or vec.shape[0] < 1:
            raise GeometryError(
                f"vectors must have shape (n_views, 12) with n_views >= 1, got {np.shape(self.vectors)}"
            )
        if not np.all(np.isfinite(vec)):
            bad = np.unique(np.nonzero(~np.isfinite(vec))[0])
            raise GeometryError(f"vectors must be finite; views {bad[:10].tolist()} hold NaN or Inf")
        u, v = vec[:, 6:9], vec[:, 9:12]
        nu, nv = np.linalg.norm(u, axis=1), np.linalg.norm(v, axis=1)
        if np.any(nu == 0) or np.any(nv == 0):
            bad = np.nonzero((nu == 0) | (nv == 0))[0]
            raise GeometryError(f"detector steps u and v must be non-zero (zero pixel pitch) at views {bad[:10].tolist()}")
        normal = np.cross(u, v)
        area = np.linalg.norm(normal, axis=1)
        if np.any(area <= 1e-12 * nu * nv):
            bad = np.nonzero(area <= 1e-12 * nu * nv)[0]
            raise GeometryError(f"detector steps u and v must not be parallel, at views {bad[:10].tolist()}")
        if self.kind == "cone":
            src, d = vec[:, 0:3], vec[:, 3:6]
            dist = np.einsum("ij,ij->i", d - src, normal / area[:, None])
            scale = np.maximum(np.linalg.norm(d - src, axis=1), np.maximum(nu, nv))
            bad = np.nonzero(np.abs(dist) <= 1e-9 * scale)[0]
            if bad.size:
                raise GeometryError(
                    f"the source must not lie in the detector plane (source on the detector) at views {bad[:10].tolist()}"
                )
        else:
            ray = vec[:, 0:3]
            cosang = np.abs(np.einsum("ij,ij->i", ray, normal)) / (np.linalg.norm(ray, axis=1) * area + 1e-300)
            bad = np.nonzero(cosang <= 1e-9)[0]
            if bad.size:
                raise GeometryError(
                    f"the ray direction must not be zero or parallel to the detector at views {bad[:10].tolist()}"
                )
        vec.setflags(write=False)
        object.__setattr__(self, "vectors", vec)

    # -- constructors / conversions ------------------------------------------
    @classmethod
    def from_vectors(cls, vectors, det_shape, kind: str = "cone") -> "VectorGeometry":
        """Build from plain ``(n_views, 12)`` rows (ASTRA ``cone_vec`` / ``parallel3d_vec``)."""
        return cls(vectors, det_shape, kind)

    @classmethod
    def from_astra(cls, proj_geom: dict) -> "VectorGeometry":
        """Build from an ASTRA projection-geometry dict of type ``cone_vec`` or ``parallel3d_vec``."""
        try:
            typ = proj_geom["type"]
            rows, cols = proj_geom["DetectorRowCount"], proj_geom["DetectorColCount"]
            vec = proj_geom["Vectors"]
        except (KeyError, TypeError) as exc:
            raise GeometryError(
                "proj_geom must be an ASTRA dict with 'type', 'DetectorRowCount', "
                f"'DetectorColCount' and 'Vectors'; missing {exc}"
            ) from None
        kinds = {v: k for k, v in _ASTRA_TYPES.items()}
        if typ not in kinds:
            raise GeometryError(
                f"proj_geom['type'] must be 'cone_vec' or 'parallel3d_vec', got {typ!r}; "
                "convert circular ASTRA geometries with astra.geom_2vec first"
            )
        return cls(vec, (int(rows), int(cols)), kinds[typ])

    def to_astra(self) -> dict:
        """ASTRA projection-geometry dict (``cone_vec`` / ``parallel3d_vec``).

        The rows are identical: pdvc uses ASTRA's vector layout. Note that
        ASTRA's volume geometry must then describe the same voxel grid.
        """
        return {
            "type": _ASTRA_TYPES[self.kind],
            "DetectorRowCount": self.det_shape[0],
            "DetectorColCount": self.det_shape[1],
            "Vectors": np.array(self.vectors),
        }

    # -- basic accessors -----------------------------------------------------
    @property
    def n_views(self) -> int:
        return self.vectors.shape[0]

    def __len__(self) -> int:
        return self.n_views

    def __repr__(self) -> str:
        return f"VectorGeometry(kind={self.kind!r}, n_views={self.n_views}, det_shape={self.det_shape})"

    def __eq__(self, other) -> bool:
        if not isinstance(other, VectorGeometry):
            return NotImplemented
        return (
            self.kind == other.kind
            and self.det_shape == other.det_shape
            and np.array_equal(self.vectors, other.vectors)
        )

    __hash__ = None  # type: ignore[assignment]

    @property
    def src(self) -> np.ndarray:
        """Source positions (cone) or ray directions (parallel), ``(n_views, 3)``."""
        return self.vectors[:, 0:3]

    @property
    def ray(self) -> np.ndarray:
        """Ray directions, ``(n_views, 3)``: given for parallel beam, central ray for cone beam."""
        if self.kind == "parallel":
            return self.vectors[:, 0:3]
        return self.vectors[:, 3:6] - self.vectors[:, 0:3]

    @property
    def det_center(self) -> np.ndarray:
        return self.vectors[:, 3:6]

    @property
    def u(self) -> np.ndarray:
        return self.vectors[:, 6:9]

    @property
    def v(self) -> np.ndarray:
        return self.vectors[:, 9:12]

    @property
    def det_normal(self) -> np.ndarray:
        """Unit normal ``u x v / |u x v|`` of each view's detector, ``(n_views, 3)``."""
        n = np.cross(self.u, self.v)
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def pixel_centers(self, view: int, rows=None, cols=None) -> np.ndarray:
        """World centres of pixels of one view, ``(len(rows), len(cols), 3)``."""
        nr, nc = self.det_shape
        rows = np.arange(nr) if rows is None else np.asarray(rows, np.float64)
        cols = np.arange(nc) if cols is None else np.asarray(cols, np.float64)
        vec = self.vectors[view]
        return (
            vec[3:6]
            + (np.asarray(cols, np.float64)[None, :, None] - (nc - 1) / 2) * vec[6:9]
            + (np.asarray(rows, np.float64)[:, None, None] - (nr - 1) / 2) * vec[9:12]
        )

    def project_points(self, points) -> np.ndarray:
        """Detector coordinates ``(row, col)`` (pixel units) of world points.

        Parameters
        ----------
        points : (n_points, 3) array, xyz

        Returns
        -------
        (n_views, n_points, 2) float64
            Continuous ``(row, col)`` pixel coordinates, 0 at the first pixel
            centre. Used for reprojection-error metrics.
        """
        p = np.asarray(points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise GeometryError(f"points must have shape (n_points, 3), got {p.shape}")
        nr, nc = self.det_shape
        d, u, v = self.det_center, self.u, self.v
        n = np.cross(u, v)
        if self.kind == "cone":
            s = self.src
            direction = p[None, :, :] - s[:, None, :]
            origin = np.broadcast_to(s[:, None, :], direction.shape)
        else:
            direction = np.broadcast_to(self.ray[:, None, :], (self.n_views, p.shape[0], 3))
            origin = np.broadcast_to(p[None, :, :], direction.shape)
        denom = np.einsum("vpk,vk->vp", direction, n)
        t = np.einsum("vpk,vk->vp", d[:, None, :] - origin, n) / denom
        hit = origin + t[..., None] * direction - d[:, None, :]
        # solve hit = a u + b v in the detector plane (least squares exact here)
        uu = np.einsum("vk,vk->v", u, u)
        vv = np.einsum("vk,vk->v", v, v)
        uv = np.einsum("vk,vk->v", u, v)
        hu = np.einsum("vpk,vk->vp", hit, u)
        hv = np.einsum("vpk,vk->vp", hit, v)
        det = uu * vv - uv * uv
        a = (hu * vv[:, None] - hv * uv[:, None]) / det[:, None]
        b = (hv * uu[:, None] - hu * uv[:, None]) / det[:, None]
        return np.stack([b + (nr - 1) / 2, a + (nc - 1) / 2], axis=-1)

    # -- transformations (all return new objects) ----------------------------
    def __getitem__(self, index) -> "VectorGeometry":
        """Views selected by an int, slice, index array or boolean mask."""
        sel = self.vectors[index]
        if sel.ndim == 1:
            sel = sel[None, :]
        if sel.shape[0] == 0:
            raise GeometryError(f"view selection {index!r} selects no view")
        return VectorGeometry(sel, self.det_shape, self.kind)

    def binned(self, factor: int) -> "VectorGeometry":
        """Detector binned by ``factor`` x ``factor`` pixels.

        Pixel steps are multiplied by ``factor`` and the shape divided by it
        (rounded down: trailing rows/columns that do not fill a bin are
        dropped, as :func:`pdvc.projectors.bin_projections` does), so binned
        pixel ``(I, J)`` is the mean of original pixels ``factor*I ...
        factor*I + factor - 1`` (same for columns).
        """
        if not isinstance(factor, (int, np.integer)) or isinstance(factor, bool) or factor < 1:
            raise GeometryError(f"factor must be a positive int, got {factor!r}")
        s = int(factor)
        nr, nc = self.det_shape
        nr2, nc2 = nr // s, nc // s
        if nr2 < 1 or nc2 < 1:
            raise GeometryError(f"factor {s} is larger than the detector {self.det_shape}")
        vec = np.array(self.vectors)
        u, v = vec[:, 6:9].copy(), vec[:, 9:12].copy()
        # centre of the kept pixels moves by half the dropped remainder
        vec[:, 3:6] += (s * nc2 - nc) / 2 * u + (s * nr2 - nr) / 2 * v
        vec[:, 6:9] = s * u
        vec[:, 9:12] = s * v
        return VectorGeometry(vec, (nr2, nc2), self.kind)

    def cropped(self, rows: tuple[int, int], cols: tuple[int, int]) -> "VectorGeometry":
        """Geometry of the detector window ``[r0, r1) x [c0, c1)``."""
        nr, nc = self.det_shape
        (r0, r1), (c0, c1) = rows, cols
        if not (0 <= r0 < r1 <= nr and 0 <= c0 < c1 <= nc):
            raise GeometryError(
                f"rows and cols must be ranges inside the detector {self.det_shape}, got rows={rows}, cols={cols}"
            )
        vec = np.array(self.vectors)
        shift_c = (c0 + c1 - 1) / 2 - (nc - 1) / 2
        shift_r = (r0 + r1 - 1) / 2 - (nr - 1) / 2
        vec[:, 3:6] += shift_c * vec[:, 6:9] + shift_r * vec[:, 9:12]
        return VectorGeometry(vec, (r1 - r0, c1 - c0), self.kind)

    def transformed(self, rotation, translation=(0.0, 0.0, 0.0)) -> "VectorGeometry":
        """Scanner moved rigidly: points ``x -> R x + t`` for every view.

        ``rotation`` is a rotation vector (3,) or matrix (3, 3), shared by all
        views; for per-view motion of the *sample* use :meth:`apply_poses`.
        """
        rot = np.asarray(rotation, np.float64)
        R = rotvec_to_matrix(rot) if rot.shape == (3,) else rot
        if R.shape != (3, 3):
            raise GeometryError(f"rotation must be a rotation vector (3,) or matrix (3, 3), got shape {rot.shape}")
        t = np.asarray(translation, np.float64).reshape(3)
        vec = np.array(self.vectors)
        parts = vec.reshape(-1, 4, 3)
        out = parts @ R.T
        out[:, 1] += t
        if self.kind == "cone":
            out[:, 0] += t
        return VectorGeometry(out.reshape(-1, 12), self.det_shape, self.kind)

    def apply(self, poses) -> "VectorGeometry":
        """Geometry that sees the sample at ``poses`` (a :class:`pdvc.geometry.Poses` of this scan)."""
        from ._poses import Poses

        if not isinstance(poses, Poses):
            raise GeometryError(f"poses must be a pdvc.geometry.Poses, got {type(poses).__name__}")
        if poses.n_views != self.n_views:
            raise GeometryError(f"poses have {poses.n_views} views, the geometry {self.n_views}")
        return self.apply_poses(poses.rotvecs, poses.translations)

    def apply_poses(self, rotvecs, translations, *, center=None) -> "VectorGeometry":
        """Geometry that sees the sample at per-view rigid poses.

        The sample's true position at view k is ``x -> R_k x + t_k`` of the
        volume frame (``R_k`` from rotation vector ``rotvecs[k]``). If
        ``center`` is given, the pose is read about that point instead:
        ``x -> R_k (x - c) + c + translations[k]``. The returned geometry is
        the nominal one mapped by the inverse pose, ``src' = R_kᵀ(src - t_k)``
        (same for ``d``), ``u' = R_kᵀ u``, ``v' = R_kᵀ v`` (parallel beam:
        ``ray' = R_kᵀ ray``), exactly (no linearisation).

        Parameters
        ----------
        rotvecs : (n_views, 3) or (3,) array, radians (axis x angle)
        translations : (n_views, 3) or (3,) array, length units, xyz
        center : (3,) array, optional
        """
        n = self.n_views
        tr = np.asarray(translations, np.float64)
        try:
            rv = np.broadcast_to(np.asarray(rotvecs, np.float64), (n, 3))
            tr = np.broadcast_to(tr, (n, 3))
        except ValueError:
            raise GeometryError(
                f"rotvecs and translations must have shape ({n}, 3) or (3,), "
                f"got {np.shape(rotvecs)} and {np.shape(translations)}"
            ) from None
        if not (np.all(np.isfinite(rv)) and np.all(np.isfinite(tr))):
            raise GeometryError("rotvecs and translations must be finite")
        R = rotvec_to_matrix(rv)  # (n, 3, 3)
        if center is not None:
            c = np.asarray(center, np.float64).reshape(3)
            tr = tr + c - np.einsum("nij,j->ni", R, c)
        parts = np.array(self.vectors).reshape(n, 4, 3)
        if self.kind == "cone":
            parts[:, 0] -= tr
        parts[:, 1] -= tr
        # R^T x for each of the four 3-vectors: x_i R_ij summed over i
        out = np.einsum("nki,nij->nkj", parts, R)
        return VectorGeometry(out.reshape(n, 12), self.det_shape, self.kind)
