"""Drawing helpers the stages' drawings (`treereg_viewer/stages/<name>.py`) share: panel text and tables
(`common`), the scan layer under every stage (`scan_layer`), the fitted sections of the Fits and Fine
stages (`fits`), the cross-section inspector (`cross_section`), the stem's motion (`motion`) and 2-D
images (`images`)."""
