"""Learning stage: audio features and the audio-to-viseme mapping model (paper section 5)."""
