"""How the TextGrids in this folder were made: by Praat itself (Praat 6.1.38 inside praat-parselmouth 0.4.7).

Not run by the tests (parselmouth is no dependency of the project); run it by hand in an environment that has
`pip install praat-parselmouth`. The tests check that our reader gives the same tiers for every file, so the
binary and chronological layouts are checked against what Praat really writes, not against our reading of them.
"""

import parselmouth
from parselmouth.praat import call

tg = call("Create TextGrid", 0.0, 1.5, "phones words pitch", "pitch")
call(tg, "Insert boundary", 1, 0.25)
call(tg, "Insert boundary", 1, 0.5)
call(tg, "Set interval text", 1, 2, "@")
call(tg, "Set interval text", 1, 3, "aI")
call(tg, "Insert boundary", 2, 0.5)
call(tg, "Set interval text", 2, 1, "héllo ʃ")
call(tg, "Insert point", 3, 0.7, "H*")
call(tg, "Set tier name", 2, "wörds")
tg.save("binary.TextGrid", parselmouth.Data.FileFormat.BINARY)
tg.save("long_utf16.TextGrid", parselmouth.Data.FileFormat.TEXT)
tg.save("short_utf16.TextGrid", parselmouth.Data.FileFormat.SHORT_TEXT)
call(tg, "Save as chronological text file", "chronological.TextGrid")

astral = call("Create TextGrid", 0.0, 1.0, "phones", "")
call(astral, "Insert boundary", 1, 0.4)
call(astral, "Set interval text", 1, 1, "𝒜x")  # outside the BMP: a surrogate pair in UTF-16
call(astral, "Set interval text", 1, 2, 'say "hi"')
astral.save("binary_astral.TextGrid", parselmouth.Data.FileFormat.BINARY)
