"""Frame sources behind one interface (base.Source): the synthetic world, video, image
folders, cameras, GStreamer, replay; factory.open_source() picks one from the config, and
rig decides the run's stereo rig."""
