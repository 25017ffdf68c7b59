"""One drawing function per stage result type.

Each takes the scene, the stage's layer root, the published `Snapshot` and the `ViewState`, and
returns the scene handles it made (so the drawer can remove them on the next draw) and the
`PanelContent` for the docked panel. Renderers only draw results: every coordinate they show comes
from a result or from `treereg_core.rigid.apply_transform` with a result's transform.
"""
