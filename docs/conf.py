"""Sphinx configuration: the pages under docs/ (Markdown, read by myst-parser) and the API reference, built by
autodoc and napoleon from the numpy-style docstrings of the installed package (``make docs``)."""

project = "kpd"
author = "the kpd developers"
copyright = "2026, the kpd developers"

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "myst_parser",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build"]

# The pages link to each other's sections as page.md#a-heading (GitHub's anchors), which these anchors resolve.
myst_heading_anchors = 3

# numpy-style docstrings: "points : (N, 3) float64" parameter lines, Returns, Raises.
napoleon_google_docstring = False
napoleon_numpy_docstring = True
napoleon_use_rtype = False

autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_typehints_format = "short"
autoclass_content = "both"

html_theme = "alabaster"
html_static_path = []
html_title = "kpd"

# One page per module, found by walking the packages (kpd.io, kpd.scan, kpd.train, kpd.viewer, kpd.export), so a
# module split in two appears without editing the pages. Written into docs/api/_generated at build time.
extensions.append("sphinx.ext.autosummary")
autosummary_generate = True
templates_path = ["_templates"]
# A package documents what its own modules define, not the names it re-exports (kpd.io.Mesh is kpd.mesh.Mesh).
autodoc_default_options["ignore-module-all"] = True

# Many docstrings write "name : what it is" without a separate type; napoleon renders the description as the type
# and cross-references its words, and a word such as "keypoints" or "vertices" names attributes of several classes.
# Those ambiguous matches are all this silences (an unknown target never warns: nitpicky is off).
suppress_warnings = ["ref.python"]
