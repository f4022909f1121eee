"""Pictures layer: fields, vector fields, curves and animations (matplotlib), pictures of files, and
:func:`show`, one call that draws fields, states, trajectories and files inline in Jupyter or to PNG/GIF/MP4.

``y`` (axis 1) is up in every picture; 3-D fields are shown as a slice (``axis=``, ``index=``) or a projection
(``projection='max'`` / ``'mean'`` / ``'min'``).
"""

from phisim.viz.plot import (
    AXIS_NAMES,
    PLANES,
    PROJECTIONS,
    animate,
    axis_index,
    draw_mask,
    ffmpeg_available,
    make_animation,
    mask_view,
    new_figure,
    panel_layout,
    plane_grid,
    plot_curves,
    plot_field,
    plot_training_curves,
    plot_vector_field,
    save_animation,
    save_figure,
    view_label,
    volume_view,
)
from phisim.viz.plotfile import (
    DERIVED,
    animate_file,
    default_field,
    default_out_dir,
    field_frames,
    field_label,
    file_animation,
    obstacle_of,
    plot_file,
    plot_frames,
    plot_training_file,
)
from phisim.viz.show import Picture, show

__all__ = [
    "new_figure", "plot_field", "plot_vector_field", "plot_curves", "animate", "make_animation", "save_animation",
    "save_figure", "ffmpeg_available", "draw_mask", "plot_training_curves",
    "AXIS_NAMES", "PLANES", "PROJECTIONS", "axis_index", "volume_view", "mask_view", "plane_grid", "view_label",
    "panel_layout",
    "DERIVED", "field_frames", "field_label", "obstacle_of", "plot_frames", "animate_file", "file_animation",
    "plot_training_file", "plot_file", "default_out_dir", "default_field",
    "show", "Picture",
]
