from cnnps.pipeline.cli import main

main()
