"""A render run on disk: frames, the render job, run files and the one atomic
writer, frame images and the selection layer."""
