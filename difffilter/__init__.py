"""difffilter."""
