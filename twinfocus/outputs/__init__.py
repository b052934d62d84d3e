"""Pictures: PNGs of images, focusing results and depth maps, no display needed."""
