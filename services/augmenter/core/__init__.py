"""Pure augmentation math (numpy only): projection, group actions, relabelling."""
