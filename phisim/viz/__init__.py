"""Pictures layer: fields, vector fields, curves and animations (matplotlib), and pictures of files."""

from phisim.viz.plot import (
    animate,
    draw_mask,
    ffmpeg_available,
    new_figure,
    plot_curves,
    plot_field,
    plot_training_curves,
    plot_vector_field,
    save_figure,
)
from phisim.viz.plotfile import (
    DERIVED,
    animate_file,
    field_frames,
    obstacle_of,
    plot_file,
    plot_frames,
    plot_training_file,
)

__all__ = [
    "new_figure", "plot_field", "plot_vector_field", "plot_curves", "animate", "save_figure", "ffmpeg_available",
    "draw_mask", "plot_training_curves",
    "DERIVED", "field_frames", "obstacle_of", "plot_frames", "animate_file", "plot_training_file", "plot_file",
]
