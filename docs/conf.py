"""Sphinx configuration for torchrl_causal."""

import os
import sys

os.environ.setdefault("MUJOCO_GL", "egl")
sys.path.insert(0, os.path.abspath(".."))

project = "torchrl_causal"
author = "torchrl_causal developers"
copyright = "2026, torchrl_causal developers"
release = "0.1.0"

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.napoleon",
    "sphinx.ext.intersphinx",
    "sphinx.ext.viewcode",
    "sphinx.ext.mathjax",
]
autosummary_generate = True
# Package __init__ files re-export their submodules' classes; documenting them
# there too would give every class two targets. Each class is documented once,
# in the module that defines it.
autodoc_default_options = {"members": True, "show-inheritance": True, "ignore-module-all": True}
# Base classes from other projects (gymnasium, torch) have docstrings in other
# styles; do not inherit them.
autodoc_inherit_docstrings = False
autodoc_member_order = "bysource"
autodoc_typehints = "description"
napoleon_google_docstring = True
napoleon_numpy_docstring = False

# Nothing may download at build time on CI: each project's online inventory is
# tried first and, when the machine is offline, an empty local inventory is the
# fallback (cross-links to these projects then render as plain text).
_OFFLINE_INV = os.path.join(os.path.dirname(__file__), "_intersphinx", "offline.inv")
intersphinx_mapping = {
    "python": ("https://docs.python.org/3", (None, _OFFLINE_INV)),
    "torch": ("https://docs.pytorch.org/docs/stable", (None, _OFFLINE_INV)),
    "torchrl": ("https://docs.pytorch.org/rl/stable", (None, _OFFLINE_INV)),
    "tensordict": ("https://docs.pytorch.org/tensordict/stable", (None, _OFFLINE_INV)),
}
intersphinx_timeout = 2
suppress_warnings = ["intersphinx.external", "config.cache"]
nitpicky = False

templates_path = []
exclude_patterns = ["_build"]
html_theme = "furo"
html_static_path = ["_static"]
html_title = "torchrl_causal"
