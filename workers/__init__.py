"""trapflow's algorithm plugins, installed as `trapflow_workers`; each names its Worker class."""
