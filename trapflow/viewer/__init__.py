"""The live web viewer and Prometheus metrics: `trapflow start --view`, `trapflow view`."""
