"""What a command tells the user about rejected inputs: the first few, one line each, and what to do about the
common ones. The rejects table holds every reason, but a user who sees only "3 rejected" has to run a second
command to learn that, say, the corpus has transcripts and no timings; the first lines usually say it all."""

from collections.abc import Mapping, Sequence

SHOWN = 5
"""Rejects printed one per line before `... and N more`."""
_LINE_CHARS = 300

ALIGNER_HINT = ("these utterances have no alignment (phone timings): for English speech, put its words in <name>.txt "
                "beside the audio and ingest aligns them itself; otherwise run a forced aligner such as the Montreal "
                "Forced Aligner (`mfa align CORPUS english_us_arpa english_us_arpa ALIGNED`, then put each "
                "<name>.TextGrid beside its audio), or use `visemeflow speak` / `visemeflow predict`, which need no "
                "alignment")
TRANSCRIPT_HINT = ("English transcripts beside their audio (<name>.lab or <name>.txt) are aligned by ingest itself; "
                   "these could not be: check that each transcript is what is said; speech the built-in aligner "
                   "(pocketsphinx, English only) cannot follow needs an aligner of its own, such as the Montreal "
                   "Forced Aligner (`mfa align CORPUS MODEL DICTIONARY ALIGNED`, a TextGrid beside each audio), or "
                   "`visemeflow speak` / `visemeflow predict`, which need no alignment")
TRANSCRIPT_ERRORS = ("TranscriptNotEnglish", "TranscriptNotAligned")


def reject_lines(rows: Sequence[Mapping[str, object]], shown: int = SHOWN) -> list[str]:
    """One line per reject for the first `shown`: `[stage] ErrorType: utterance: reason (file)`, the file added
    where the reason does not name it; then `... and N more`."""
    lines = []
    for row in rows[:shown]:
        message = str(row.get("message") or "").strip()
        message = message.splitlines()[0] if message else ""
        uid, path = row.get("utterance_id"), row.get("path")
        if uid and not message.startswith(str(uid)):
            message = f"{uid}: {message}"
        if path and str(path) not in message:
            message = f"{message} ({path})"
        if len(message) > _LINE_CHARS:
            message = message[: _LINE_CHARS - 3] + "..."
        stage = f"[{row['stage']}] " if row.get("stage") else ""
        lines.append(f"  {stage}{row.get('error_type')}: {message}")
    if len(rows) > shown:
        lines.append(f"  ... and {len(rows) - shown} more")
    return lines


def reject_advice(rows: Sequence[Mapping[str, object]]) -> list[str]:
    """What to do about the kinds of reject that have one usual cause (no alignment: an aligner, or `speak`)."""
    advice = []
    if any(row.get("error_type") == "MissingAlignment" for row in rows):
        transcripts = any("transcript without times" in str(row.get("message")) for row in rows)
        advice.append(("the .lab files found are transcripts without times; " if transcripts else "") + ALIGNER_HINT)
    if any(row.get("error_type") in TRANSCRIPT_ERRORS for row in rows):
        advice.append(TRANSCRIPT_HINT)
    return advice
