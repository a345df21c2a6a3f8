"""Looking at results (docs/dense.md): PNG snapshot, offline HTML page, Open3D line sets."""

from omni_sfm.view.render import ViewOutputs, html_document, make_view, write_html, write_png
from omni_sfm.view.scene import ViewScene, load_view_scene

__all__ = ["ViewOutputs", "ViewScene", "html_document", "load_view_scene", "make_view",
           "write_html", "write_png"]
