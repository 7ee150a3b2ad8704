from cubecloud_cli.cli import main

main()
