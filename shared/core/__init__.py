"""The bottom layer: errors, atomic files, the shared-data path, lazy exports and the process's
CPU budget (``cpu_budget``, with numba's threading policy in ``shared.core.threads``); for
numba kernels, how they are compiled (``shared.core.jit``: ``kernel`` and ``helper``), the
Morton bit spreading (``shared.core.morton``), ``popcount`` (``shared.core.bits``) and a start-up
without ``scipy.linalg`` (``shared.core.numba_start``).

Everything else in ``shared/`` may import these; they import nothing of Graylight's.
``cpu_budget`` resolves lazily: its module imports numba, and importing the package loads none.
"""

from shared.core.datapaths import shared_data_dir
from shared.core.errors import GraylightError, InputError
from shared.core.files import atomic_file, read_json, write_json_atomic
from shared.core.lazy import lazy_exports
from shared.core.paths import confine, open_regular, read_bounded

_, __getattr__, __dir__ = lazy_exports(__name__, {"cpu_budget": "threads"})

__all__ = ["GraylightError", "InputError", "atomic_file", "confine", "cpu_budget", "lazy_exports", "open_regular", "read_bounded", "read_json", "shared_data_dir",
           "write_json_atomic"]  # fmt: skip
