"""Landing uploaded block files: content-addressed under ``blocks/<sha256>.las|laz``,
checked, fsynced and renamed into place before they are recorded, so an accepted
upload is never lost."""

from __future__ import annotations

import contextlib
import dataclasses
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pipeline.errors import InputError
from service.permissions import FILE_MODE
from service.quotas import StorageQuotaExceeded

if TYPE_CHECKING:
    from service.db.jobstore import Store


def _sniff_suffix(path: Path) -> str:
    """``.laz`` if the LAS header says the points are compressed, else ``.las``."""
    with open(path, "rb") as fh:
        head = fh.read(105)
    if len(head) > 104 and head[:4] == b"LASF" and head[104] & 0x80:
        return ".laz"
    return ".las"


def _as_las(tmp_path: Path, size_bytes: int, filename: str | None, crs_epsg: int | None,
            columns: str | None) -> tuple[Path, int]:
    """The LAS/LAZ file of an upload and its size: the upload itself, or the LAZ its
    points were converted to (the upload is then removed)."""
    # here: laspy and pyproj (~0.6 s) are no cost of `orchard schedules --help`, which imports service.schedules
    from pipeline.formats import sniff
    from pipeline.formats.convert import to_laz

    named_las = (filename or "").lower().endswith((".las", ".laz"))  # said to be LAS: its checks say why it is not
    try:
        fmt = "las" if named_las else sniff(tmp_path)
        if fmt == "las":
            if crs_epsg is not None or columns is not None:
                raise InputError("crs and columns are for PLY, PCD, E57 and text files; a LAS/LAZ file states its own CRS")
            return tmp_path, size_bytes
        laz = tmp_path.with_name(tmp_path.name + ".laz")
        to_laz(tmp_path, laz, fmt=fmt, crs_epsg=crs_epsg, columns=columns)
    except InputError as exc:
        raise InputError(str(exc).replace(tmp_path.name, filename or "the upload")) from None
    tmp_path.unlink()
    return laz, laz.stat().st_size


def _fsync_dir(path: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def info_record(info: Any) -> dict[str, Any]:
    """A BlockInfo as JSON-able dict (without the server-side path)."""
    rec = dataclasses.asdict(info) if dataclasses.is_dataclass(info) else dict(info)
    rec.pop("path", None)
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in rec.items()}


def accept_block(
    store: Store,
    *,
    blocks_dir: Path,
    tenant_id: str,
    tmp_path: Path,
    sha256: str,
    size_bytes: int,
    filename: str | None,
    crs_epsg: int | None = None,
    columns: str | None = None,
) -> tuple[dict[str, Any], bool]:
    """Validate a fully written temporary file and land it as a block of ``tenant_id``.

    A PLY, PCD, E57 or text file is first converted to LAZ
    (`pipeline.formats.convert.to_laz`, with ``crs_epsg`` and a text file's ``columns``),
    and the LAZ is the block's file. The header is checked with
    `pipeline.blockinfo.read_info` (InputError if not a usable LAS/LAZ file). The file is
    stored under the checksum of what was sent (``sha256``), fsynced, renamed into place,
    and only then recorded. The temporary file is always gone afterwards. Returns
    ``(block, created)``; the same file twice gives the same block.
    """
    # here: laspy and pyproj (~0.6 s) are no cost of `orchard schedules --help`, which imports service.schedules
    from pipeline.blockinfo import read_info

    tmp_path = Path(tmp_path)
    try:
        existing = store.blocks.by_sha(tenant_id, sha256)
        if existing is not None and Path(existing["path"]).exists():
            return existing, False
        if size_bytes == 0:
            raise InputError("the file is empty (0 bytes); upload a LAS or LAZ file")
        tmp_path, size_bytes = _as_las(tmp_path, size_bytes, filename, crs_epsg, columns)
        store.quotas.check_storage(tenant_id, size_bytes)
        suffix = _sniff_suffix(tmp_path)
        typed = tmp_path.with_suffix(suffix)
        os.replace(tmp_path, typed)
        tmp_path = typed
        try:
            info = read_info(str(tmp_path))
        except InputError as exc:
            text = str(exc).replace(tmp_path.name, filename or "the upload")
            raise InputError(text) from None
        blocks_dir.mkdir(parents=True, exist_ok=True)
        final = blocks_dir / f"{sha256}{'.laz' if getattr(info, 'compressed', suffix == '.laz') else '.las'}"
        landed = not final.exists()
        if landed:
            with open(tmp_path, "rb+") as fh:
                os.fchmod(fh.fileno(), FILE_MODE)  # a farm's file: the service user's alone
                os.fsync(fh.fileno())
            os.replace(tmp_path, final)
            _fsync_dir(blocks_dir)
        try:
            return store.blocks.insert(
                tenant_id=tenant_id,
                sha256=sha256,
                path=str(final),
                filename=filename,
                size_bytes=size_bytes,
                info=info_record(info),
            )
        except StorageQuotaExceeded:  # another upload of the tenant's took the room meanwhile
            if landed and not store.blocks.file_used_any_tenant(str(final)):
                final.unlink(missing_ok=True)
            raise
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
