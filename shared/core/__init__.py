"""The bottom layer: errors, atomic files, the shared-data path and lazy exports (and, imported
by the kernel modules only, numba's threading policy: ``shared.core.threads``).

Everything else in ``shared/`` may import these; they import nothing of Graylight's.
"""

from shared.core.datapaths import shared_data_dir
from shared.core.errors import GraylightError, InputError
from shared.core.files import atomic_file, read_json, write_json_atomic
from shared.core.lazy import lazy_exports

__all__ = ["GraylightError", "InputError", "atomic_file", "lazy_exports", "read_json", "shared_data_dir", "write_json_atomic"]
