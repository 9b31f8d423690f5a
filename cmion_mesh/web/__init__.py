"""The browser: the body's page, the live view of a mesh, their web server, speech."""
