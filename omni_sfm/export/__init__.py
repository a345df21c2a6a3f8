"""Hand the estimated poses to other tools: COLMAP models (pycolmap), TUM files, Open3D."""
