"""export/ (and the formats of io/formats/ it writes): `mcsplat export`'s formats, outliers and refusals."""
