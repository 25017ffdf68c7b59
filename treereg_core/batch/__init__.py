"""Campaigns: many trees registered in one run (`treereg batch`).

`jobs` finds the trees (a folder of tree folders, or a CSV manifest), `tree` registers one tree and
returns everything to write (it never raises: a failing tree is an outcome like any other),
`runner` runs the trees in a process pool or on a Dask cluster and writes each tree's files as it
finishes (so a run can be resumed), `report` writes the summary CSVs and the HTML report,
`picture` draws the small top and side views the report shows.
"""
