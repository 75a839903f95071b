"""What a name may be: clips, libraries, models and tasks are named by folders and files.

Here, at the foundation, so that both the warehouse (which checks names) and the label schemas
(which publish the task id's pattern) use one rule.
"""

from __future__ import annotations

import re

NAME = re.compile(r"^(?=[.-]*[A-Za-z0-9_])[A-Za-z0-9_-][A-Za-z0-9_.-]{0,199}$")
"""A clip, library, model or task name: a folder and file name. At most 200 letters, digits, '_',
'.' and '-'; not starting with '.'; not only '-' and '.'. It may start with '-': 1 in 64 YouTube
ids does, and CAD-Estate names a clip by its video's id (``-0AK9iy8y0c_122914456``)."""
