// phalanx interop check: an ARIA client exercising the motion commands ARIA programs use,
// against any ARCOS robot (the phalanx emulator, AMRISim, a P3DX). Built and run by
// tests/interop/test_aria_on_emulator.py; prints one "PHALANX key=value ..." line per
// step, which the test parses. Poses are ARIA's own (mm, deg), read from the robot's SIPs.
//
//   g++ -std=c++14 -I$ARIA/include aria_motion_check.cpp -L$ARIA/lib -lAria -lpthread -ldl -lrt
//   ./a.out -rh 127.0.0.1 -rrtp 8101

#include "Aria/Aria.h"
#include "Aria/ArRobotConfigPacketReader.h"

#include <cstdio>

namespace {

void report(ArRobot &robot, const char *step)
{
  robot.lock();
  std::printf("PHALANX step=%s x=%.1f y=%.1f th=%.2f vel=%.1f rotvel=%.2f\n", step,
              robot.getX(), robot.getY(), robot.getTh(), robot.getVel(), robot.getRotVel());
  robot.unlock();
  std::fflush(stdout);
}

// Wait (at most timeout_ms) until `done` holds and the robot is at rest.
template <typename Done>
bool settle(ArRobot &robot, Done done, unsigned int timeout_ms)
{
  ArTime started;
  while (started.mSecSince() < timeout_ms) {
    robot.lock();
    const bool finished = done() && ArMath::fabs(robot.getVel()) < 1.0 &&
                          ArMath::fabs(robot.getRotVel()) < 0.2;
    robot.unlock();
    if (finished) return true;
    ArUtil::sleep(50);
  }
  return false;
}

void stopAndSettle(ArRobot &robot)
{
  robot.lock();
  robot.stop();
  robot.unlock();
  settle(robot, [] { return true; }, 5000);
}

}  // namespace

int main(int argc, char **argv)
{
  Aria::init();
  ArArgumentParser parser(&argc, argv);
  parser.loadDefaultArguments();
  ArRobot robot;
  ArRobotConnector connector(&parser, &robot);
  if (!connector.connectRobot()) {
    std::printf("PHALANX step=connect ok=0\n");
    Aria::exit(1);
    return 1;
  }
  robot.runAsync(true);
  robot.lock();
  robot.enableMotors();
  robot.unlock();
  ArUtil::sleep(500);  // a few SIPs in: the battery readings are the robot's
  robot.lock();
  const ArRobotConfigPacketReader *config = robot.getOrigRobotConfig();
  std::printf(
      "PHALANX step=config trans_vel_max=%d rot_vel_max=%d trans_accel=%d trans_decel=%d "
      "rot_accel=%d rot_decel=%d watchdog=%d trans_vel_top=%d battery=%.1f real_battery=%.1f\n",
      config->getTransVelMax(), config->getRotVelMax(), config->getTransAccel(),
      config->getTransDecel(), config->getRotAccel(), config->getRotDecel(),
      config->getWatchdog(), config->getTransVelTop(), robot.getBatteryVoltage(),
      robot.getRealBatteryVoltage());
  robot.unlock();
  report(robot, "start");

  // Both wheels backwards at 200 mm/s for 2 s (VEL2 with a negative argument).
  robot.lock();
  robot.setVel2(-200, -200);
  robot.unlock();
  ArUtil::sleep(2000);
  stopAndSettle(robot);
  report(robot, "vel2_back");

  // Turn on the spot with VEL2: left -100, right +100 mm/s for 2 s.
  robot.lock();
  robot.setVel2(-100, 100);
  robot.unlock();
  ArUtil::sleep(2000);
  stopAndSettle(robot);
  report(robot, "vel2_turn");

  robot.lock();
  robot.setHeading(90);
  robot.unlock();
  settle(robot, [&robot] { return robot.isHeadingDone(0.5); }, 15000);
  report(robot, "heading_90");

  robot.lock();
  robot.setDeltaHeading(-45);
  robot.unlock();
  settle(robot, [&robot] { return robot.isHeadingDone(0.5); }, 15000);
  report(robot, "delta_heading_-45");

  robot.lock();
  robot.move(1000);
  robot.unlock();
  settle(robot, [&robot] { return robot.isMoveDone(5); }, 20000);
  report(robot, "move_1000");

  robot.lock();
  robot.move(-500);
  robot.unlock();
  settle(robot, [&robot] { return robot.isMoveDone(5); }, 20000);
  report(robot, "move_-500");

  robot.stopRunning();
  robot.waitForRunExit();
  std::printf("PHALANX step=end ok=1\n");
  Aria::exit(0);
  return 0;
}
