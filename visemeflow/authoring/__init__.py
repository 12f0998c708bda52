"""Authoring a character's visemes, done once per character rather than per utterance: deformation transfer of the
16 visemes onto a new face (`transfer`) and the automatic markers that pair the two faces (`automarkers`, FaceMesh
on rendered views). It sits above `animation` (it reads and writes characters with its loaders and glTF writer) and
is the only part of the character side that needs `tracking`."""
