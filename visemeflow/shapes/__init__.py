"""Shapes by name: naming conventions and how the 16 curves drive them (`conventions`: ours, ARKit 52, Oculus 15,
mapping CSVs, detection), captured-animation readers (`livelink`: Live Link Face CSV) and the ARKit -> visemes fit
(`capture`). `data/`: the retargeting tables. Imports `rig` (characters) and `visemes`."""
