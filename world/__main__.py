from world.main import console

console()
