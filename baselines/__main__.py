"""``python -m baselines``: the registered methods as a Markdown table (:func:`baselines.methods.markdown_table`)."""

import sys

from baselines.methods import markdown_table

sys.stdout.write(markdown_table())
