"""The commands, over the library: `cli` (``feedbench …``, argument parsing), `console` (the
console script: Ctrl-C ends with one line), `demo`, `campaign`, `tune`, `closure` and
`exchange` (UFF58 / CSV export). Each is a thin workflow over `bench`, `report`, `api` and
the rooms below them; nothing in the library imports a command."""
