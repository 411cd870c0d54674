from avatarperfect_cli.cli import app

app(prog_name="avatarperfect")
