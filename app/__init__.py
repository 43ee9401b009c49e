"""shiftkit's applications: the `shiftkit` command line (`cli.py`, one module per command in
`commands/`) and the programs that drive the simulator or a format tied to it (`collect.py`: scripted
experts recorded into datasets; `demo.py`: the demo pipeline; `importers/`: importers of formats
defined by an env). They sit above every other package: nothing below imports them
(docs/architecture.md)."""
