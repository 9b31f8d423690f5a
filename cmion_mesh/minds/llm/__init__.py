"""A language-model mind: any OpenAI-compatible chat-completions endpoint drives the body."""
