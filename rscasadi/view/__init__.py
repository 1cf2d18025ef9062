"""`rscasadi view`: a solution or a model as a 3D animation in one self-contained HTML file
(MeshCat's viewer), and as a GIF for documents."""
from rscasadi.view.gif import write_gif
from rscasadi.view.html import write_html
from rscasadi.view.scene import Scene, scene_of

__all__ = ["Scene", "scene_of", "write_gif", "write_html"]
