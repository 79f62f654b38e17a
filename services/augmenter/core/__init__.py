"""Pure augmentation math (numpy only): projection, group actions, relabelling, and what the
physics audit counts as valid."""
