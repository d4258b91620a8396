from swarm.cli import console

console()
