"""A companion moving between embodiments: the handshake, custody, identity documents, the ledger, invitations."""
