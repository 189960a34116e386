"""Reading and writing USD: the Phrt schema and plugin, opening a stage, what it
holds for rendering, camera paths, validation, authoring and inspection."""
