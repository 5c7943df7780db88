"""Reports: figures (matplotlib, Agg) and the Markdown/HTML report builder."""
