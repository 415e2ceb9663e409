"""Writing ``.npz`` archives byte for byte reproducibly: the same arrays give the same bytes (fixed zip
timestamps), so a seeded run can be checked by comparing files. ``np.load`` reads them; no pickles.
"""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np


def write_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Like ``np.savez_compressed`` but with fixed timestamps; written to a temporary file, then renamed, so
    a reader never sees half a file. uint8 arrays (JPEG and PNG bytes, compressed already) are stored, the
    rest deflated; 0-d arrays stay 0-d."""
    tmp = path.with_suffix(".tmp")
    with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=6) as archive:
        for key, value in arrays.items():
            value = np.ascontiguousarray(value) if np.ndim(value) else np.asarray(value)
            buffer = io.BytesIO()
            np.lib.format.write_array(buffer, value, allow_pickle=False)
            info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_STORED if value.dtype == np.uint8 else zipfile.ZIP_DEFLATED
            archive.writestr(info, buffer.getvalue())
    tmp.replace(path)
