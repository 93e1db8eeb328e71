"""sfm.synthetic.scenes."""
