"""An embodiment and what it is made of: configuration, competency manager, execution, rules, stand-ins."""
