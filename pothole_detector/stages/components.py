"""Connected components over the selected superpixels, with the paper's filters."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numba
import numpy as np

from ..backend import Backend, to_host
from . import box_cpu
from .superpixels import upsample_labels

EIGHT_CONNECTED = np.ones((3, 3), dtype=bool)


@dataclass(frozen=True)
class FarCorners:
    """The far corner regions of the area that has disparities: int32 (H,) ``first`` and
    ``last`` column with a disparity in each row (0 and W - 1 in a row without any) and the
    regions' ``side`` (px, 0: no regions). In the top ``side`` rows, the first and last
    ``side`` columns of each row's valid span are corner (a disparity map's left border is
    never valid, so the image corner itself is not where the data ends). Only the top
    corners: the road's disparity grows down the image (the seed pass accepts no other
    road), so they are where the road is farthest, seen at the most grazing angle and
    departs most from its model, while a pothole in a near corner is seen best. Potholes
    that reach into them need more evidence (measure.reportable)."""

    first: Any
    last: Any
    side: int


def far_corners(backend: Backend, valid: Any, fraction: float) -> FarCorners:
    """The far corner regions of the HxW bool ``valid`` area with side ``fraction`` x the short
    image side; on the GPU one kernel (kernels/components.cu), nothing read back."""
    xp = backend.xp
    height, width = valid.shape
    side = int(round(fraction * min(height, width)))
    if backend.is_gpu:
        first = xp.empty(height, dtype=xp.int32)
        last = xp.empty(height, dtype=xp.int32)
        _kernel(backend, "row_extents")(
            ((height + 7) // 8,), (256,),
            (xp.ascontiguousarray(valid, dtype=xp.bool_), np.int32(height), np.int32(width),
             first, last))
        return FarCorners(first, last, side)
    return _far_corners(xp, valid, side)


def _far_corners(xp: Any, valid: Any, side: int) -> FarCorners:
    """far_corners with array functions (the reference of kernels/components.cu's)."""
    width = valid.shape[1]
    has_valid = valid.any(axis=1)
    first = xp.where(has_valid, xp.argmax(valid, axis=1), 0).astype(xp.int32)
    last = xp.where(has_valid, width - 1 - xp.argmax(valid[:, ::-1], axis=1),
                    width - 1).astype(xp.int32)
    return FarCorners(first, last, side)


def in_far_corner(corners: FarCorners, rows: Any, cols: Any) -> Any:
    """Bool, per pixel (int arrays ``rows``, ``cols``): whether it lies in a far corner
    region: the top ``side`` rows, within ``side`` columns of its row's valid span."""
    side = corners.side
    first, last = corners.first[rows], corners.last[rows]
    return (rows < side) & ((cols < first + side) | (cols > last - side))


def pothole_components(backend: Backend, candidate: Any, valid: Any, superpixel_labels: Any,
                       n_superpixels: int, min_superpixels: int,
                       factor: int = 1, capacity: int | None = None,
                       counts: Any = None, inconsistent: Any = None, bumps: Any = None) -> Any:
    """The components stage: label the 8-connected components of the bool ``candidate`` mask
    (of the HxW shape of the bool ``valid``); drop components that hold fewer than
    ``min_superpixels`` superpixels (HxW
    ``superpixel_labels``), of whose superpixels more than half are flagged in the bool
    (n_superpixels,) ``inconsistent`` (where given), or that touch a superpixel flagged in
    the bool (n_superpixels,) ``bumps`` (where given; a pixel of it is an 8-neighbour of
    one of that superpixel's pixels). Returns int32 HxW labels numbered 1..k, 0 elsewhere.

    ``candidate`` is HxW, or the mask on the SLIC grid reduced by ``factor`` whose
    nearest-neighbour enlargement (superpixels.upsample_labels) is the HxW mask: enlarging by
    whole pixels keeps 8-connectivity and the raster order of components, so labelling the
    small mask and enlarging the labels gives the same labels with factor^2 fewer pixels.

    Writes the backend int32 (3,) ``counts`` where given: components found, kept, and overflow
    (1 when more than ``capacity`` were found: the GPU's tables then missed some, and a caller
    that needs them all runs the stage again with the found count as capacity). On the GPU
    union-find and filter kernels (kernels/components.cu) with nothing read back, unless
    ``capacity`` is None (then the found count, read back).
    """
    xp = backend.xp
    if backend.is_gpu:
        small, found = label_on_device(backend, candidate)
        if capacity is None:
            capacity = max(int(to_host(found)[0]), 1)
        counts = xp.empty(3, dtype=xp.int32) if counts is None else counts
        return filter_on_device(backend, small, found, valid, superpixel_labels, n_superpixels,
                                min_superpixels, factor, capacity, counts, inconsistent, bumps)
    components, count = label_components(backend, candidate)
    components = upsample_labels(backend, components, factor, valid.shape)
    if count == 0:
        labels, kept = components.astype(xp.int32), 0
    else:
        keep = xp.ones(count + 1, dtype=bool)
        keep[0] = False
        pairs = components.ravel().astype(xp.int64) * n_superpixels + superpixel_labels.ravel()
        present = xp.bincount(pairs[components.ravel() > 0],
                              minlength=(count + 1) * n_superpixels)
        held = present.reshape(count + 1, n_superpixels) > 0
        superpixel_count = held.sum(axis=1)
        keep &= superpixel_count >= min_superpixels
        if inconsistent is not None:
            keep &= 2 * (held & inconsistent[None, :]).sum(axis=1) <= superpixel_count
        if bumps is not None:
            keep[beside(xp, components, bumps[superpixel_labels])] = False
            keep[0] = False
        labels, kept = relabel(xp, components, keep)
    if counts is not None:
        counts[...] = (count, kept, int(capacity is not None and count > capacity))
    return labels


def beside(xp: Any, components: Any, marked: Any) -> Any:
    """The labels (int (m,), with repeats) of the components of the int HxW ``components``
    (0 off them) of which a pixel is an 8-neighbour of a ``marked`` pixel (bool HxW) off every
    component."""
    height, width = components.shape
    padded = xp.pad(components, 1)
    outside = marked & (components == 0)
    found = [padded[1 + dv:1 + dv + height, 1 + du:1 + du + width][outside]
             for dv in (-1, 0, 1) for du in (-1, 0, 1) if dv or du]
    return xp.concatenate(found)


def components_found(backend: Backend, candidate: Any, valid: Any, superpixel_labels: Any,
                     n_superpixels: int, min_superpixels: int,
                     factor: int = 1, inconsistent: Any = None, bumps: Any = None
                     ) -> tuple[Any, int]:
    """:func:`pothole_components` with every component and the kept count read back:
    (int32 HxW labels, k)."""
    counts = backend.xp.zeros(3, dtype=backend.xp.int32)
    labels = pothole_components(backend, candidate, valid, superpixel_labels, n_superpixels,
                                min_superpixels, factor, counts=counts,
                                inconsistent=inconsistent, bumps=bumps)
    return labels, int(to_host(counts)[1])


def join_pieces(backend: Backend, labels: Any, reach_px: int, count: Any,
                factor: int = 1, grid: Any = None, depressed: Any = None,
                bridge_px: int = 0) -> Any:
    """One depression, one component: the components of the int32 HxW ``labels`` (0 off them)
    that come within about 2 ``reach_px`` px of each other, or that a depressed stretch of
    road joins, are joined, and all are numbered 1..m; m goes into the backend int32 (1,)
    ``count``. A shallow, wide pothole often shows as pieces, its shallowest parts under the
    threshold: gaps narrower than the segmentation resolves (half a superpixel, with
    ``reach_px`` a quarter of one) do not part a depression, nor do gaps of road that lies
    below the road around it (``depressed``: bool per superpixel, of the SLIC ``grid`` labels)
    within ``bridge_px`` px of a component, while road at the level of the road around it
    between two potholes keeps them apart.
    Worked out on the grid reduced by ``factor`` (the SLIC grid's; a cell is on where any of
    its pixels is labelled): its cells within ceil(``reach_px`` / ``factor``) cells of a labelled
    one, in rows and in columns, and its depressed cells within ceil(``bridge_px`` /
    ``factor``) cells, are labelled as 8-connected components in raster order of their first
    cell that holds a labelled one, and each labelled pixel takes its cell's. Returns the
    int32 HxW labels; nothing read back. On the GPU five small kernels and the device
    labelling (kernels/components.cu)."""
    if backend.is_gpu:
        return _join_on_device(backend, labels, reach_px, count, factor, grid, depressed,
                               bridge_px)
    xp = backend.xp
    on = labels > 0
    cells = _cells_on(np.ascontiguousarray(labels), factor)
    near = _dilated(backend, cells, -(-reach_px // factor)) > 0
    bridging = depressed is not None and bridge_px > 0
    if bridging:
        rows, cols = min(grid.shape[0], cells.shape[0]), min(grid.shape[1], cells.shape[1])
        bridge = xp.zeros_like(near)
        bridge[:rows, :cols] = xp.take(depressed, grid[:rows, :cols])
        near |= bridge & (_dilated(backend, cells, -(-bridge_px // factor)) > 0)
    joined, found = label_components(backend, near)
    if bridging:
        # bridges that reach no component are no component: number those that hold one
        holds = xp.zeros(joined.size + 1, dtype=bool)
        holds[joined * (cells > 0)] = True
        holds[0] = False
        joined = renumbering(xp, holds)[joined]
        found = holds.sum()
    count[...] = found
    return xp.where(on, upsample_labels(backend, joined.astype(xp.int32), factor, on.shape),
                    0).astype(xp.int32)


def _join_on_device(backend: Backend, labels: Any, reach_px: int, count: Any, factor: int,
                    grid: Any, depressed: Any, bridge_px: int) -> Any:
    """:func:`join_pieces` on the GPU, the same labels."""
    xp = backend.xp
    i32 = np.int32
    labels = xp.ascontiguousarray(labels, dtype=xp.int32)
    height, width = labels.shape
    rows, cols = -(-height // factor), -(-width // factor)
    size = rows * cols
    cell_grid, block = ((size + 255) // 256,), (256,)
    cells = xp.empty((rows, cols), dtype=xp.uint8)
    _kernel(backend, "join_cells")(
        cell_grid, block, (labels, i32(height), i32(width), i32(factor), i32(rows), i32(cols),
                           cells))
    bridging = depressed is not None and bridge_px > 0
    reach = -(-reach_px // factor)
    bridge_reach = -(-bridge_px // factor) if bridging else 0
    near_rows = xp.empty((rows, cols), dtype=xp.uint8)
    bridge_rows = xp.empty((rows, cols), dtype=xp.uint8)
    _kernel(backend, "join_rows")(
        cell_grid, block, (cells, i32(rows), i32(cols), i32(reach), i32(bridge_reach),
                           near_rows, bridge_rows))
    near = xp.empty((rows, cols), dtype=xp.bool_)
    flags = xp.ascontiguousarray(depressed, dtype=xp.bool_) if bridging else near
    slic_grid = xp.ascontiguousarray(grid, dtype=xp.int32) if bridging else cells
    rows_in, cols_in = slic_grid.shape if bridging else (0, 0)
    _kernel(backend, "join_near")(
        cell_grid, block, (near_rows, bridge_rows, i32(rows), i32(cols), i32(reach),
                           i32(bridge_reach), flags, slic_grid, i32(rows_in), i32(cols_in),
                           i32(bridging), near))
    joined, found = label_on_device(backend, near)
    table = joined
    if bridging:
        holds = xp.zeros(size + 1, dtype=xp.bool_)
        _kernel(backend, "join_holds")(cell_grid, block, (joined, cells, i32(size), holds))
        table = renumbering(xp, holds)
        found = holds.sum()
    count[...] = found
    out = xp.empty((height, width), dtype=xp.int32)
    _kernel(backend, "join_labels")(
        (-(-width // 32), -(-height // 8)), (32, 8),
        (labels, joined, table, i32(bridging), i32(height), i32(width), i32(factor), i32(rows),
         i32(cols), out))
    return out


@numba.njit(parallel=True, cache=True)
def _cells_on(labels: np.ndarray, factor: int) -> np.ndarray:
    """uint8 (ceil(H / factor), ceil(W / factor)): 1 where any pixel of the cell's ``factor`` x
    ``factor`` square (clipped at the map's edge) of the HxW ``labels`` is above 0."""
    height, width = labels.shape
    rows, cols = -(-height // factor), -(-width // factor)
    cells = np.zeros((rows, cols), dtype=np.uint8)
    for i in numba.prange(rows):
        for v in range(i * factor, min((i + 1) * factor, height)):
            for u in range(width):
                if labels[v, u] > 0:
                    cells[i, u // factor] = 1
    return cells


def _dilated(backend: Backend, cells: Any, reach: int) -> Any:
    """``cells`` (uint8 2D) dilated by a square of ``reach`` cells each way."""
    size = 2 * reach + 1
    if not backend.is_gpu:
        return box_cpu.square_maximum(np.ascontiguousarray(cells, dtype=np.uint8), size)
    return backend.ndimage.maximum_filter1d(
        backend.ndimage.maximum_filter1d(cells, size, axis=0), size, axis=1)


def renumbering(xp: Any, keep: Any) -> Any:
    """int32 (k+1,): label i's new label, 1..m in order where the bool (k+1,) ``keep`` is
    true, 0 where not; on the backend, nothing read back."""
    return xp.cumsum(keep).astype(xp.int32) * keep


def relabel(xp: Any, labels: Any, keep: Any) -> tuple[Any, int]:
    """Keep the labels where the bool (k+1,) ``keep`` is true, renumbered 1..m in order."""
    new_ids = renumbering(xp, keep)
    kept = int(to_host(keep.sum()))
    return new_ids[labels].astype(xp.int32), kept


def label_components(backend: Backend, mask: Any) -> tuple[Any, int]:
    """8-connected components of an HxW bool mask: (int32 HxW labels 1..k in raster order of
    each component's first pixel, 0 off the mask; k). scipy.ndimage.label on the CPU; on the
    GPU :func:`label_on_device` and one readback of k."""
    if not backend.is_gpu:
        labels, count = backend.ndimage.label(mask, structure=EIGHT_CONNECTED)
        return labels.astype(np.int32), int(count)
    labels, count = label_on_device(backend, mask)
    return labels, int(to_host(count)[0])


def label_on_device(backend: Backend, mask: Any) -> tuple[Any, Any]:
    """:func:`label_components` by union-find kernels (kernels/components.cu), nothing read
    back: (int32 HxW labels, the component count as a device int32 (1,))."""
    xp = backend.xp
    height, width = mask.shape
    size = height * width
    if size == 0:
        return xp.zeros((height, width), dtype=xp.int32), xp.zeros(1, dtype=xp.int32)
    parent = xp.empty(size, dtype=xp.int32)
    is_root = xp.empty(size, dtype=xp.int32)
    labels = xp.empty((height, width), dtype=xp.int32)
    grid, block = ((size + 255) // 256,), (256,)
    _kernel(backend, "label_init")(
        grid, block, (xp.ascontiguousarray(mask, dtype=xp.bool_), parent, np.int32(size)))
    _kernel(backend, "label_merge")(
        grid, block, (parent, np.int32(height), np.int32(width)))
    _kernel(backend, "label_flatten")(grid, block, (parent, is_root, np.int32(size)))
    root_count = xp.cumsum(is_root, dtype=xp.int32)
    _kernel(backend, "label_number")(
        grid, block, (parent, root_count, labels, np.int32(size)))
    return labels, root_count[-1:]


# Components the device filters hold tables for without knowing the count: per component two
# int32 and a bit per superpixel.
COMPONENT_CAPACITY = 1023
COMPONENT_TABLE_BYTES = 8 * 2**20


def device_capacity(n_superpixels: int) -> int:
    """How many components :func:`pothole_components` can filter without a readback for
    ``n_superpixels`` superpixels (1023, fewer when their tables would pass 8 MiB)."""
    row_bytes = 4 * (2 + _words(n_superpixels))
    return max(15, min(COMPONENT_CAPACITY, COMPONENT_TABLE_BYTES // row_bytes - 1))


def _words(n_superpixels: int) -> int:
    return -(-max(n_superpixels, 1) // 32)


def filter_on_device(backend: Backend, small: Any, count: Any, valid: Any,
                     superpixel_labels: Any, n_superpixels: int, min_superpixels: int,
                     factor: int, capacity: int, counts: Any, inconsistent: Any = None,
                     bumps: Any = None) -> Any:
    """The bump, superpixel and consistency filters of pothole_components on labels
    ``small`` of the (reduced) candidate mask with the device component ``count``:
    kernels/components.cu reads them at full resolution by index arithmetic (superpixel,
    bump and consistency marks, the keep/renumber table in one block, the final labels).
    Writes ``counts`` as :func:`components_on_device` does."""
    xp = backend.xp
    height, width = valid.shape
    small_height, small_width = small.shape
    i32 = np.int32
    words = _words(n_superpixels)
    marks = xp.zeros((capacity + 1) * (3 + words), dtype=xp.int32)
    touched, held, flagged_held = (marks[k * (capacity + 1):(k + 1) * (capacity + 1)]
                                   for k in range(3))
    present = marks[3 * (capacity + 1):].view(xp.uint32)
    flagged, bumped = (xp.zeros(max(n_superpixels, 1), dtype=xp.bool_) if given is None
                       else xp.ascontiguousarray(given, dtype=xp.bool_)
                       for given in (inconsistent, bumps))
    size = height * width
    grid = ((size + 255) // 256,)
    _kernel(backend, "component_marks")(
        grid, (256,),
        (small, xp.ascontiguousarray(superpixel_labels, dtype=xp.int32), flagged, bumped,
         i32(height), i32(width), i32(factor), i32(small_height), i32(small_width),
         i32(words), i32(capacity), touched, held, flagged_held, present))
    new_id = xp.empty(capacity + 1, dtype=xp.int32)
    _kernel(backend, "component_keep")(
        (1,), (1024,), (touched, held, flagged_held, count, i32(capacity),
                        i32(min_superpixels), new_id, counts[1:2]))
    counts[0:1] = count
    counts[2:3] = touched[0:1]
    labels = xp.empty((height, width), dtype=xp.int32)
    _kernel(backend, "component_relabel")(
        grid, (256,), (small, new_id, labels, i32(height), i32(width), i32(factor),
                       i32(small_height), i32(small_width), i32(capacity)))
    return labels


def _kernel(backend: Backend, name: str) -> Any:
    """Kernel ``name`` of kernels/components.cu."""
    return backend.kernel("components.cu", name, {})

