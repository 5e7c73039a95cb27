"""Sphinx configuration of the API reference (`make docs`: HTML in docs/_build/html).

Built with -W (a warning fails the build) and without network: no intersphinx.
"""

project = "feedbench"
author = "feedbench maintainers"
extensions = ["sphinx.ext.autodoc"]
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_default_options = {"members": True, "show-inheritance": True}
default_role = "code"
html_theme = "alabaster"
exclude_patterns = ["_build"]
